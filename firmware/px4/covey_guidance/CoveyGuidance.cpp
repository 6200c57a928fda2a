/*
 * CoveyGuidance.cpp - see CoveyGuidance.hpp. No guidance logic here: data in,
 * covey_guidance_step() (decision hold + separation filter around covey_command()),
 * data out.
 */
#include "CoveyGuidance.hpp"

#include <px4_platform_common/log.h>

#include <string.h>

using namespace time_literals;

CoveyGuidance::CoveyGuidance() :
	ModuleParams(nullptr),
	ScheduledWorkItem(MODULE_NAME, px4::wq_configurations::nav_and_controllers)
{
	covey_traffic_init(&_traffic);
}

bool CoveyGuidance::init()
{
	update_parameters();
	return covey_config_check(&_config) == COVEY_OK;
}

void CoveyGuidance::update_parameters()
{
	updateParams();
	_config.separation_m = _param_separation_m.get();
	_config.cruise_speed_m_s = _param_cruise_speed_m_s.get();
	_config.max_neighbour_age_us = (uint64_t)(1e6f * math::max(_param_nbr_age_s.get(), 0.f));
	_config.max_own_age_us = (uint64_t)(1e6f * math::max(_param_own_age_s.get(), 0.f));
	_config.max_neighbours = math::constrain((int32_t)_param_max_neighbours.get(), (int32_t)0,
				 (int32_t)COVEY_MAX_NEIGHBOURS);
	_guidance = covey_guidance_defaults(&_config); // trained decision period, filter on
	_guidance.safety_filter = _param_filter.get() ? 1 : 0;
	_guidance.sparse_rule = _param_sparse.get() ? 1 : 0; // used only with the filter
	// the network's berth (0: 1.25 m per 3 m of CVY_SEP_M with the filter); the filter keeps CVY_SEP_M
	_guidance.policy.separation_m = covey_told_separation_m(_config.separation_m, _guidance.safety_filter,
					_param_policy_separation_m.get());
	_guidance.safety.dt_s = 1.f / math::constrain(_param_rate_hz.get(), 1.f, 50.f);
	// the berth kept from traffic that does not cooperate (0: CVY_SEP_M); the filter takes the
	// whole correction for it (covey_safety.h)
	_guidance.safety.non_cooperative_radius_m = math::max(_param_nc_separation_m.get(), 0.f);
	// the berth kept from a manned aircraft (its ADS-B emitter category, covey_emitter_is_manned)
	_guidance.safety.manned_radius_m = math::max(_param_manned_separation_m.get(), 0.f);
	_fence_pending = true; // the zones' clearance follows CVY_SEP_M
	covey_hold_reset(&_hold); // decide afresh with the new parameters
	const float rate_hz = math::constrain(_param_rate_hz.get(), 1.f, 50.f);
	ScheduleOnInterval((uint32_t)(1e6f / rate_hz));
}

void CoveyGuidance::ingest_traffic()
{
	transponder_report_s report;

	// transponder_report is queued: drain everything that arrived since the last cycle
	while (_transponder_sub.update(&report)) {
		const bool usable = (report.flags & transponder_report_s::PX4_ADSB_FLAGS_VALID_COORDS)
				    && (report.flags & transponder_report_s::PX4_ADSB_FLAGS_VALID_HEADING)
				    && report.icao_address != (uint32_t)_param_own_icao.get()
				    && _ref.isInitialized();

		if (!usable) {
			continue;
		}

		float north_m = NAN;
		float east_m = NAN;
		_ref.project(report.lat, report.lon, north_m, east_m);
		const covey_vehicle_t v{north_m, east_m, report.heading, report.timestamp};
		// velocity over ground from course and horizontal speed (the filter needs it)
		const float speed_m_s = (report.flags & transponder_report_s::PX4_ADSB_FLAGS_VALID_VELOCITY)
					? report.hor_velocity : 0.f;
		// covey's own neighbours carry its marking (covey_traffic.h); any other report (a real
		// ADS-B receiver, a station's intruder forwarded by the relay) does not cooperate
		char callsign[sizeof(report.callsign) + 1] {};
		memcpy(callsign, report.callsign, sizeof(report.callsign));
		const int32_t ours = covey_traffic_is_covey(report.icao_address, callsign, report.emitter_type);
		covey_traffic_put_classified(&_traffic, report.icao_address, &v, speed_m_s * cosf(report.heading),
					     speed_m_s * sinf(report.heading), !ours,
					     covey_emitter_is_manned(report.emitter_type)); // refuses non-finite/out of range
	}
}

void CoveyGuidance::ingest_fence()
{
	mission_s mission;

	// PX4 bumps geofence_id whenever a fence is uploaded (covey's agents upload the fleet plan)
	if (_mission_sub.update(&mission) && mission.geofence_id != _fence_id) {
		_fence_id = mission.geofence_id;
		_fence_pending = true;
	}

	if (_fence_pending && _ref.isInitialized()) {
		_fence_pending = false;
		load_fence();
	}
}

void CoveyGuidance::load_fence()
{
	// dataman's fence: a stats entry at index 0, the items after it (as navigator's geofence)
	mission_stats_entry_s stats{};
	int32_t n = 0;

	if (_param_zones.get()
	    && _dataman.readSync(DM_KEY_FENCE_POINTS, 0, reinterpret_cast<uint8_t *>(&stats), sizeof(stats))) {
		for (int i = 0; i < math::min((int)stats.num_items, kMaxFenceItems); i++) {
			mission_fence_point_s pt{};

			if (!_dataman.readSync(DM_KEY_FENCE_POINTS, i + 1, reinterpret_cast<uint8_t *>(&pt), sizeof(pt))) {
				break;
			}

			covey_fence_item_t &it = _fence_items[n++];
			_ref.project(pt.lat, pt.lon, it.pos_n_m, it.pos_e_m);
			it.command = pt.nav_cmd;
			const bool circle = pt.nav_cmd == COVEY_FENCE_CIRCLE_INCLUSION || pt.nav_cmd == COVEY_FENCE_CIRCLE_EXCLUSION;
			it.vertex_count = circle ? 0 : pt.vertex_count;
			it.radius_m = circle ? pt.circle_radius : 0.f;
		}

		if (stats.num_items > kMaxFenceItems) {
			n = kMaxFenceItems + 1; // refused by the core as too many, with the reason below
		}
	}

	// the core converts and checks (covey_fence_zones); on a fault no zones are kept
	_fence_status = n > kMaxFenceItems ? COVEY_ERR_RANGE
			: covey_fence_zones(&_zones, _fence_items, n, &_guidance.safety, &_fence_scratch);

	if (_fence_status != COVEY_OK) {
		_zones.n_vertices = 0;
		PX4_ERR("covey guidance: geofence not usable as keep-out zones (%s): flying without them",
			covey_status_name(_fence_status));

	} else {
		PX4_INFO("covey guidance: %d fence items, %d zone vertices kept %.1f m from", (int)n,
			 (int)_zones.n_vertices, (double)covey_zone_radius_m(&_guidance.safety));
	}
}

void CoveyGuidance::ingest_goal()
{
	vehicle_command_s cmd;

	while (_vehicle_command_sub.update(&cmd)) {
		if (cmd.command != vehicle_command_s::VEHICLE_CMD_DO_REPOSITION || !_ref.isInitialized()
		    || !PX4_ISFINITE(cmd.param5) || !PX4_ISFINITE(cmd.param6)) {
			continue;
		}

		float north_m = NAN;
		float east_m = NAN;
		_ref.project(cmd.param5, cmd.param6, north_m, east_m);
		_goal = covey_goal_t{north_m, east_m};
		// altitude: AMSL param7 -> local down; unset (NaN) keeps the current altitude
		_goal_z_m = PX4_ISFINITE(cmd.param7) ? -(cmd.param7 - _local_position.ref_alt) : _local_position.z;
		_have_goal = true;
	}
}

void CoveyGuidance::Run()
{
	if (should_exit()) {
		ScheduleClear();
		exit_and_cleanup();
		return;
	}

	if (_parameter_update_sub.updated()) {
		parameter_update_s update;
		_parameter_update_sub.copy(&update);
		update_parameters();
	}

	_local_position_sub.update(&_local_position);

	if (_local_position.xy_global && _local_position.ref_timestamp != _ref_timestamp) {
		_ref.initReference(_local_position.ref_lat, _local_position.ref_lon, _local_position.ref_timestamp);
		_ref_timestamp = _local_position.ref_timestamp;
		covey_traffic_init(&_traffic); // positions projected on the old reference are void
		_fence_pending = true;         // so are the zones
	}

	ingest_traffic();
	ingest_goal();
	ingest_fence();

	if (!_param_enable.get()) {
		return;
	}

	const hrt_abstime now = hrt_absolute_time();
	covey_traffic_prune(&_traffic, now, _config.max_neighbour_age_us);

	covey_command_t cmd{};
	float heading_rad = _heading.heading_rad;

	if (_have_goal && _local_position.xy_valid) {
		heading_rad = covey_heading_for_goal(&_heading, _local_position.x, _local_position.y, &_goal);
		const covey_vehicle_t own{_local_position.x, _local_position.y, heading_rad, _local_position.timestamp};
		const float own_vel_m_s[2] {_local_position.vx, _local_position.vy};
		// decides at the trained period (the held velocity in between), filters every tick:
		// covey neighbours reciprocally, traffic (manned aircraft at CVY_MANNED_M) with the
		// whole correction, the geofence's zones as hard lines
		covey_traffic_kinds(&_traffic, _kinds);
		covey_guidance_out_t out{};
		_last_status = covey_guidance_step_zones(&_guidance, &_hold, &own, own_vel_m_s, 0.f, &_goal,
				_traffic.report, &_traffic.vel_m_s[0][0], nullptr, _kinds,
				_traffic.n, &_zones, now, &_scratch, &out);
		_ticks++;
		_faults[math::min((int)_last_status, 4)]++;

		if (_last_status == COVEY_OK) {
			cmd.vel_n_m_s = out.vel_n_m_s;
			cmd.vel_e_m_s = out.vel_e_m_s;
			_evaluations += out.decided ? 1 : 0;
			_filtered += out.filter.changed ? 1 : 0;

			if (out.decided) {
				// the heading follows the policy's decisions, as in training (not the filter)
				covey_heading_after_command(&_heading, &out.command);
				_last_used = out.command.n_used;
			}

		} else {
			PX4_WARN("covey guidance fault: %s (holding)", covey_status_name(_last_status));
		}
	}

	// no goal, no position or a fault: cmd is zero velocity, i.e. hold here
	publish(cmd, heading_rad, now);
}

void CoveyGuidance::publish(const covey_command_t &cmd, float heading_rad, hrt_abstime now)
{
	offboard_control_mode_s mode{};
	mode.position = true;  // z is a position (altitude hold)
	mode.velocity = true;  // x, y are velocities
	mode.timestamp = now;
	_offboard_control_mode_pub.publish(mode);

	trajectory_setpoint_s sp{};
	sp.position[0] = NAN;
	sp.position[1] = NAN;
	sp.position[2] = _have_goal ? _goal_z_m : _local_position.z;
	sp.velocity[0] = cmd.vel_n_m_s;
	sp.velocity[1] = cmd.vel_e_m_s;
	sp.velocity[2] = NAN;
	sp.acceleration[0] = sp.acceleration[1] = sp.acceleration[2] = NAN;
	sp.jerk[0] = sp.jerk[1] = sp.jerk[2] = NAN;
	sp.yaw = heading_rad;  // face the direction of motion (the policy's heading)
	sp.yawspeed = NAN;
	sp.timestamp = hrt_absolute_time();
	_trajectory_setpoint_pub.publish(sp);
}

int CoveyGuidance::print_status()
{
	PX4_INFO("enabled %d, goal %d (%.1f, %.1f) m, neighbours tracked %d, used %d",
		 (int)_param_enable.get(), (int)_have_goal, (double)_goal.pos_n_m, (double)_goal.pos_e_m,
		 (int)_traffic.n, (int)_last_used);
	PX4_INFO("ticks %u, decisions %u (every %.2f s), filtered %u, filter %d", _ticks, _evaluations,
		 (double)_guidance.decision_period_s, _filtered, (int)_guidance.safety_filter);
	PX4_INFO("evaluations %u; ok %u nonfinite %u range %u stale %u; last %s", _evaluations,
		 _faults[COVEY_OK], _faults[COVEY_ERR_NONFINITE], _faults[COVEY_ERR_RANGE], _faults[COVEY_ERR_STALE],
		 covey_status_name(_last_status));
	PX4_INFO("zones: %d vertices (fence %s)", (int)_zones.n_vertices, covey_status_name(_fence_status));
	PX4_INFO("weights %s", COVEY_W_SOURCE_SHA256);
	return 0;
}

int CoveyGuidance::task_spawn(int argc, char *argv[])
{
	CoveyGuidance *instance = new CoveyGuidance();

	if (instance == nullptr) {
		PX4_ERR("alloc failed");
		return PX4_ERROR;
	}

	_object.store(instance);
	_task_id = task_id_is_work_queue;

	if (instance->init()) {
		return PX4_OK;
	}

	PX4_ERR("init failed: check CVY_SEP_M, CVY_CRUISE");
	delete instance;
	_object.store(nullptr);
	_task_id = -1;
	return PX4_ERROR;
}

int CoveyGuidance::custom_command(int argc, char *argv[])
{
	return print_usage("unknown command");
}

int CoveyGuidance::print_usage(const char *reason)
{
	if (reason) {
		PX4_WARN("%s\n", reason);
	}

	PRINT_MODULE_DESCRIPTION(
		R"DESCR_STR(
### Description
covey swarm guidance: an LSTM policy (Schlichting et al.) turns the traffic in
transponder_report and a DO_REPOSITION goal into a velocity setpoint. Switch the
vehicle to Offboard mode to fly it; faults hold position.
)DESCR_STR");

	PRINT_MODULE_USAGE_NAME("covey_guidance", "controller");
	PRINT_MODULE_USAGE_COMMAND("start");
	PRINT_MODULE_USAGE_DEFAULT_COMMANDS();
	return 0;
}

extern "C" __EXPORT int covey_guidance_main(int argc, char *argv[])
{
	return CoveyGuidance::main(argc, argv);
}
