/*
 * covey_traffic.h - what an autopilot needs around the policy core, kept out of
 * the platform shim so that it is tested on the host with the core:
 *   - a fixed-size table of the latest report per neighbour (e.g. one per
 *     ADS-B ICAO address from PX4's transponder_report);
 *   - the heading the policy sees, as the paper defines it: the direction of
 *     the last commanded displacement, or the bearing to the goal at start and
 *     whenever the goal changes.
 * Same rules as the core: caller-owned state, no malloc, float32, time passed in.
 */
#ifndef COVEY_TRAFFIC_H
#define COVEY_TRAFFIC_H

#include "covey_policy.h"
#include "covey_safety.h" /* COVEY_MAX_ABS_VEL_M_S */

#ifdef __cplusplus
extern "C" {
#endif

/* Below this commanded speed the heading is kept (hover does not turn the vehicle). */
#define COVEY_HEADING_MIN_SPEED_M_S 0.05f

/*
 * How covey's own ADSB_VEHICLE reports are told from real traffic (comms/adsb.py, the Python
 * twin, parity tested): ICAO address COVEY_TRAFFIC_ICAO_BASE | vehicle id (bit 24 set: outside
 * the 24-bit space of every real transponder), callsign "CVY<id>", emitter type UAV. Anything
 * else is traffic that does not cooperate: the filter takes the whole correction for it.
 */
#define COVEY_TRAFFIC_ICAO_BASE 0x01000000u
#define COVEY_TRAFFIC_ICAO_MASK 0xFFFF0000u
#define COVEY_ADSB_EMITTER_UAV 14

/* 1 if an ADS-B report is a covey vehicle's own (all three marks), else 0. `callsign` is the
 * report's field (up to 8 characters, NUL-padded; NULL: not ours). */
int32_t covey_traffic_is_covey(uint32_t icao_address, const char *callsign, int32_t emitter_type);

/* 1 for the ADSB_EMITTER_TYPE values of aircraft with people aboard (light, small, large,
 * high-vortex large, heavy, highly manoeuvrable, rotorcraft, glider, lighter than air,
 * parachute, ultralight), else 0. */
int32_t covey_emitter_is_manned(int32_t emitter_type);

/* Latest report per neighbour id; entries [0, n) are valid, in insertion order.
 * vel_m_s[i] is report i's (north, east) velocity, the layout covey_guidance_step takes;
 * non_cooperative[i] the layout covey_guidance_step_sky takes. */
typedef struct {
    uint32_t id[COVEY_MAX_INPUTS];
    covey_vehicle_t report[COVEY_MAX_INPUTS];
    float vel_m_s[COVEY_MAX_INPUTS][2];
    uint8_t non_cooperative[COVEY_MAX_INPUTS]; /* 1: traffic that does not avoid */
    uint8_t manned[COVEY_MAX_INPUTS];          /* 1: a manned aircraft (traffic only) */
    int32_t n;
} covey_traffic_t;

void covey_traffic_init(covey_traffic_t *t);

/*
 * Stores a report: replaces the entry with the same id, else appends, else (table
 * full) replaces the entry with the oldest stamp if the new report is newer.
 * Returns COVEY_ERR_NONFINITE / COVEY_ERR_RANGE for a report the core would
 * refuse (the table keeps its previous entry), COVEY_OK otherwise.
 */
covey_status_t covey_traffic_put(covey_traffic_t *t, uint32_t id, const covey_vehicle_t *report);

/*
 * The same with the neighbour's velocity (north, east), which the separation filter
 * needs; covey_traffic_put stores (0, 0). A non-finite velocity is refused
 * (COVEY_ERR_NONFINITE), one beyond COVEY_MAX_ABS_VEL_M_S too (COVEY_ERR_RANGE).
 */
covey_status_t covey_traffic_put_track(covey_traffic_t *t, uint32_t id,
                                       const covey_vehicle_t *report, float vel_n_m_s,
                                       float vel_e_m_s);

/*
 * The same, classified: `non_cooperative` (traffic that does not avoid; covey_traffic_is_covey
 * says which reports are covey's) and `manned` (covey_emitter_is_manned), each 0 or 1.
 * covey_traffic_put_track stores a cooperative, unmanned neighbour.
 */
covey_status_t covey_traffic_put_classified(covey_traffic_t *t, uint32_t id,
                                            const covey_vehicle_t *report, float vel_n_m_s,
                                            float vel_e_m_s, int32_t non_cooperative,
                                            int32_t manned);

/* Removes entries older than max_age_us (or stamped after now_us); returns how many. */
int32_t covey_traffic_prune(covey_traffic_t *t, uint64_t now_us, uint64_t max_age_us);

/* Each entry's kind as the filter takes it (covey_guidance_step_sky's nbr_non_cooperative,
 * covey_track_t.non_cooperative): COVEY_TRACK_COOPERATIVE, COVEY_TRACK_TRAFFIC, or
 * COVEY_TRACK_MANNED for a manned aircraft (kept manned_radius_m from). kinds holds
 * COVEY_MAX_INPUTS; returns t->n (0 on NULL or a corrupt table). */
int32_t covey_traffic_kinds(const covey_traffic_t *t, uint8_t *kinds);

/* Heading state of the own vehicle. */
typedef struct {
    float heading_rad;
    covey_goal_t goal;   /* the goal the heading was last reset for */
    int32_t valid;       /* 0 until the first reset */
} covey_heading_t;

/*
 * Call before each covey_command: on the first call or a new goal, the heading
 * becomes the bearing to the goal, atan2(g_e - p_e, g_n - p_n) (kept if the goal
 * is within 1 mm). Returns the heading to put in the own covey_vehicle_t.
 */
float covey_heading_for_goal(covey_heading_t *h, float pos_n_m, float pos_e_m,
                             const covey_goal_t *goal);

/* Call after a COVEY_OK command: heading = atan2(v_e, v_n) unless |v| < COVEY_HEADING_MIN_SPEED_M_S. */
void covey_heading_after_command(covey_heading_t *h, const covey_command_t *cmd);

#ifdef __cplusplus
}
#endif

#endif /* COVEY_TRAFFIC_H */
