/*
 * CoveyGuidance - PX4 module shim around the covey C policy core.
 *
 * Thin on purpose: every line of guidance logic (input checks, freshness,
 * neighbour table, heading, observation, network, scaling, decision hold,
 * separation filter) lives in the host-tested core (covey_policy.c,
 * covey_traffic.c, covey_safety.c, covey_guidance.c). This file only moves
 * uORB data in and out:
 *   in:  vehicle_local_position (own state, map reference),
 *        transponder_report     (neighbours, ADS-B / MAVLink ADSB_VEHICLE),
 *        vehicle_command        (goal: DO_REPOSITION lat/lon/alt),
 *        mission + dataman      (the geofence's keep-out zones, DM_KEY_FENCE_POINTS)
 *   out: trajectory_setpoint    (NED velocity, altitude hold, yaw = heading)
 *        offboard_control_mode  (so the vehicle may be switched to Offboard)
 */
#pragma once

#include <dataman_client/DatamanClient.hpp>
#include <drivers/drv_hrt.h>
#include <lib/geo/geo.h>
#include <navigator/navigation.h>
#include <px4_platform_common/defines.h>
#include <px4_platform_common/module.h>
#include <px4_platform_common/module_params.h>
#include <px4_platform_common/px4_work_queue/ScheduledWorkItem.hpp>
#include <uORB/Publication.hpp>
#include <uORB/Subscription.hpp>
#include <uORB/topics/mission.h>
#include <uORB/topics/offboard_control_mode.h>
#include <uORB/topics/parameter_update.h>
#include <uORB/topics/trajectory_setpoint.h>
#include <uORB/topics/transponder_report.h>
#include <uORB/topics/vehicle_command.h>
#include <uORB/topics/vehicle_local_position.h>

extern "C" {
#include "covey_fence.h"
#include "covey_guidance.h"
#include "covey_traffic.h"
}

class CoveyGuidance : public ModuleBase<CoveyGuidance>, public ModuleParams, public px4::ScheduledWorkItem
{
public:
	CoveyGuidance();
	~CoveyGuidance() override = default;

	static int task_spawn(int argc, char *argv[]);
	static int custom_command(int argc, char *argv[]);
	static int print_usage(const char *reason = nullptr);

	bool init();
	int print_status() override;

private:
	void Run() override;
	void update_parameters();
	void ingest_traffic();
	void ingest_goal();
	void ingest_fence();
	void load_fence();
	void publish(const covey_command_t &cmd, float heading_rad, hrt_abstime now);

	uORB::Subscription _parameter_update_sub{ORB_ID(parameter_update)};
	uORB::Subscription _local_position_sub{ORB_ID(vehicle_local_position)};
	uORB::Subscription _transponder_sub{ORB_ID(transponder_report)};
	uORB::Subscription _vehicle_command_sub{ORB_ID(vehicle_command)};
	uORB::Subscription _mission_sub{ORB_ID(mission)};
	uORB::Publication<trajectory_setpoint_s> _trajectory_setpoint_pub{ORB_ID(trajectory_setpoint)};
	uORB::Publication<offboard_control_mode_s> _offboard_control_mode_pub{ORB_ID(offboard_control_mode)};

	vehicle_local_position_s _local_position{};
	MapProjection _ref{};                 // lat/lon <-> local NED, from vehicle_local_position
	hrt_abstime _ref_timestamp{0};

	// state and scratch of the core, owned here (allocated once with the module)
	covey_config_t _config{};
	covey_guidance_config_t _guidance{};
	covey_hold_t _hold{};
	covey_guidance_scratch_t _scratch{};
	covey_traffic_t _traffic{};
	covey_heading_t _heading{};
	uint8_t _kinds[COVEY_MAX_INPUTS] {};  // each track's kind for the filter (covey_traffic_kinds)

	// keep-out zones from the autopilot's geofence (covey_fence.h), rebuilt when it changes
	static constexpr int kMaxFenceItems = COVEY_MAX_ZONE_VERTICES + COVEY_MAX_ZONE_POLYGONS;
	DatamanClient _dataman{};
	covey_fence_item_t _fence_items[kMaxFenceItems] {};
	covey_fence_scratch_t _fence_scratch{};
	covey_zones_t _zones{};
	uint32_t _fence_id{0};
	bool _fence_pending{true};  // (re)load at the next cycle with a map reference
	covey_status_t _fence_status{COVEY_OK};
	covey_goal_t _goal{};
	float _goal_z_m{NAN};
	bool _have_goal{false};

	// counters for `covey_guidance status`
	uint32_t _ticks{0};
	uint32_t _evaluations{0};
	uint32_t _filtered{0};
	uint32_t _faults[5] {};
	covey_status_t _last_status{COVEY_OK};
	int32_t _last_used{0};

	DEFINE_PARAMETERS(
		(ParamBool<px4::params::CVY_EN>) _param_enable,
		(ParamFloat<px4::params::CVY_SEP_M>) _param_separation_m,
		(ParamFloat<px4::params::CVY_POL_SEP_M>) _param_policy_separation_m,
		(ParamFloat<px4::params::CVY_CRUISE>) _param_cruise_speed_m_s,
		(ParamFloat<px4::params::CVY_RATE_HZ>) _param_rate_hz,
		(ParamBool<px4::params::CVY_FILTER>) _param_filter,
		(ParamBool<px4::params::CVY_SPARSE>) _param_sparse,
		(ParamFloat<px4::params::CVY_NBR_AGE>) _param_nbr_age_s,
		(ParamFloat<px4::params::CVY_OWN_AGE>) _param_own_age_s,
		(ParamInt<px4::params::CVY_MAX_NBR>) _param_max_neighbours,
		(ParamInt<px4::params::CVY_OWN_ICAO>) _param_own_icao,
		(ParamFloat<px4::params::CVY_NC_SEP_M>) _param_nc_separation_m,
		(ParamFloat<px4::params::CVY_MANNED_M>) _param_manned_separation_m,
		(ParamBool<px4::params::CVY_ZONES>) _param_zones
	)
};
