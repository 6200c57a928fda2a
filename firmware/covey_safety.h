/*
 * covey_safety.h - the separation filter of covey, in C99: the same ORCA
 * half-planes and 2-D linear program as policy/safety.py (van den Berg et al.,
 * "Reciprocal n-body collision avoidance", 2011).
 *
 * Each vehicle alone, from its neighbours' positions and velocities, changes
 * the preferred velocity (the policy's) as little as possible, in the
 * Euclidean sense, so that it stays outside every neighbour's velocity
 * obstacle for time_horizon_s, taking `responsibility` of the effort. When no
 * velocity satisfies every half-plane, the largest violation is minimised
 * (ORCA's fallback), so the output always exists.
 *
 * Same rules as covey_policy.h: caller-owned scratch, no malloc, float32,
 * inputs checked with isfinite then range, faults as covey_status_t with a
 * zero (hover) output.
 */
#ifndef COVEY_SAFETY_H
#define COVEY_SAFETY_H

#include "covey_policy.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Input ranges beyond COVEY_MAX_ABS_POS_M: a finite value beyond these is COVEY_ERR_RANGE. */
#define COVEY_MAX_ABS_VEL_M_S 1.0e3f          /* any vehicle's velocity component */
#define COVEY_SAFETY_MIN_RADIUS_M 0.01f
#define COVEY_SAFETY_MAX_RADIUS_M 1000.0f
#define COVEY_SAFETY_MAX_MARGIN 10.0f         /* margin in [0, this] */
#define COVEY_SAFETY_MIN_TIME_S 1.0e-3f       /* time_horizon_s and dt_s in [this, max] */
#define COVEY_SAFETY_MAX_TIME_S 1000.0f
#define COVEY_SAFETY_MAX_SIGMA_K 10.0f        /* sigma_k in [0, this] */
#define COVEY_SAFETY_MAX_SIGMA_M 1000.0f      /* a track's pos_sigma_m in [0, this] */
#define COVEY_SAFETY_MAX_RECOVER_SHARE 10.0f  /* recover_speed_share in [0, this] */

/* Filter parameters in world units (policy/safety.py SafetyConfig, same defaults). */
typedef struct {
    float radius_m;        /* [0.01, 1000]: combined radius kept between centres (the separation), 3 */
    float margin;          /* [0, 10]: relative padding on radius_m, 0.2 */
    float time_horizon_s;  /* [1e-3, 1000]: how far ahead velocity obstacles look, 4 */
    float dt_s;            /* [1e-3, 1000]: control period, used only when vehicles overlap, 0.1 */
    float max_speed_m_s;   /* [0.01, 100]: speed limit of the output, 1 */
    float responsibility;  /* (0, 1]: share of the avoidance this vehicle takes, 0.5 */
    float sigma_k;         /* [0, 10]: each pair keeps sigma_k sqrt(sigma_i^2 + sigma_j^2) more
                              between estimated centres (policy/safety.py SIGMA_K), 4; 0 (as a
                              zero-initialised config has it): estimates taken as the truth */
    float non_cooperative_radius_m; /* 0 = radius_m, else [0.01, 1000]: the separation kept
                                       from a non-cooperative track (before margin/sigma) */
    float manned_radius_m; /* 0 = as non_cooperative_radius_m, else [0.01, 1000]: the separation
                              kept from a manned track (COVEY_TRACK_MANNED), 30
                              (COVEY_SAFETY_MANNED_SEPARATION_M; policy/safety.py) */
    float recover_speed_share; /* [0, 10]: a pair inside its sigma padding, not inside the
                                  separation itself, is asked to part at up to this share of
                                  max_speed_m_s (relative), not within one dt_s
                                  (policy/safety.py RECOVER_SPEED_SHARE), 2; 0 (as a
                                  zero-initialised config has it): within one dt_s */
} covey_safety_config_t;

/* covey_safety_defaults' recover_speed_share (policy/safety.py RECOVER_SPEED_SHARE). */
#define COVEY_SAFETY_RECOVER_SPEED_SHARE 2.0f

/* covey_safety_defaults' manned_radius_m (policy/safety.py MANNED_SEPARATION_M). */
#define COVEY_SAFETY_MANNED_SEPARATION_M 30.0f

/* covey_track_t.non_cooperative values: a covey vehicle, traffic that does not avoid, and a
 * manned aircraft (traffic too, kept manned_radius_m from). Any other non-zero value is
 * COVEY_TRACK_TRAFFIC. */
#define COVEY_TRACK_COOPERATIVE 0u
#define COVEY_TRACK_TRAFFIC 1u
#define COVEY_TRACK_MANNED 2u

/* Nearer than this, two tracks are coincident: their relative position gives no direction
 * to push apart, so the ordered pair of ids gives one (policy/safety.py COINCIDENT_M). */
#define COVEY_SAFETY_COINCIDENT_M 0.01f

/* A non-cooperative pair's time horizon is at most this many time_horizon_s (or the time to
 * leave its berth at the escape speed and a horizon, if longer), and a vehicle steps
 * aside to the left only when already off the neighbour's track to the left by more than this
 * share of the pair distance (policy/safety.py NC_MAX_HORIZON_FACTOR, NC_SIDE_BIAS). */
#define COVEY_SAFETY_NC_MAX_HORIZON_FACTOR 3.0
#define COVEY_SAFETY_NC_SIDE_BIAS 0.25
/* Within r of a non-cooperative track at least as fast as us and closing: move off its track at
 * this share of max_speed_m_s or more (policy/safety.py NC_ESCAPE_SHARE). */
#define COVEY_SAFETY_NC_ESCAPE_SHARE 0.8
/* ... or faster, to clear the berth before the track arrives: (r - off) / (along / closing),
 * up to this share of the lateral speed that gains the most room before it arrives
 * (policy/traffic_rules.py clear_speed, NC_CLEAR_SHARE). */
#define COVEY_SAFETY_NC_CLEAR_SHARE 0.95
/* Moving off a fast track faster than this many max_speed_m_s is an escape (guidance never flies
 * faster): within the side band, the vehicle keeps the side it escapes to even where the track
 * line swung across it (policy/traffic_rules.py NC_KEEP_SIDE_SPEED_FACTOR, kept_offset). */
#define COVEY_SAFETY_NC_KEEP_SIDE_SPEED_FACTOR 1.5
/* The filter plans against a non-cooperative track as if it flew this share faster than it
 * reports (policy/traffic_rules.py NC_SPEED_MARGIN): traffic that does not coordinate speeds up
 * with gusts, throttle or a new leg. */
#define COVEY_SAFETY_NC_SPEED_MARGIN 0.25
/* While non-cooperative tracks add lines, the output may be as fast as the fastest of them, up to
 * this many max_speed_m_s, but no faster than max_speed_m_s along that one's track: at the cruise
 * speed alone a vehicle cannot get out of the way of traffic up to twice as fast that crosses or
 * overtakes it (policy/traffic_rules.py NC_ESCAPE_SPEED_FACTOR, escape_lines). */
#define COVEY_SAFETY_NC_ESCAPE_SPEED_FACTOR 2.0

/* A vehicle for the filter: position and velocity in the local frame (north, east). */
typedef struct {
    float pos_n_m;
    float pos_e_m;
    float vel_n_m_s;
    float vel_e_m_s;
    uint32_t id;  /* vehicle id, 0 = unknown: a
                     coincident neighbour with a known id other than own's is taken to be
                     COVEY_SAFETY_COINCIDENT_M away along a bearing hashed from both ids, the
                     opposite one for the other vehicle (policy/safety.py tie_direction) */
    float pos_sigma_m;         /* [0, 1000]: 1-sigma per axis of the position estimate (eph);
                                  0 (zero-initialised) = exact */
    uint32_t non_cooperative;  /* COVEY_TRACK_TRAFFIC (1): a neighbour that does not avoid
                                  (ADS-B, Remote ID, flown by hand): this vehicle takes the
                                  whole correction and keeps non_cooperative_radius_m;
                                  COVEY_TRACK_MANNED (2): the same, keeping manned_radius_m;
                                  0 (zero-initialised): a covey vehicle */
} covey_track_t;

/*
 * What one pair keeps (policy/safety.py pair_radius_m):
 *   r = base (1 + margin) + sigma_k sqrt(sigma_own^2 + sigma_nbr^2),
 *   base = radius_m, or non_cooperative_radius_m (when set) for a non-cooperative track, or
 *          manned_radius_m (when set) for a manned one;
 *   share = responsibility, or 1 for a non-cooperative track (it will not take its half).
 * Reach (no line beyond): r + 2 max_speed tau, or r + (max_speed + max(max_speed, |v_nbr|)) tau_j
 * for a non-cooperative track (it may be faster than us), whose own horizon is
 *   tau_j = clip((r / max_speed) (|v_own - v_nbr| / max_speed), tau, cap),
 *   cap = max(NC_MAX_HORIZON_FACTOR tau, r / (NC_ESCAPE_SPEED_FACTOR max_speed) + tau)
 * and which is passed on a leg of its cone (step aside), never fled along the line.
 */

/*
 * The LP runs in double by default: near-parallel half-planes in a dense,
 * infeasible crowd meet far away, and float32 cancellation there (|p|^2 - r^2
 * of a point 1e4 m out) can put the answer outside the speed disc. The
 * Cortex-M7 of a Pixhawk 4/6 (fpv5-d16) has a double-precision FPU; build with
 * -DCOVEY_SAFETY_DOUBLE=0 for a single-precision-only part (the output is still
 * clipped to the speed disc; parity with policy/safety.py degrades in
 * infeasible crowds, see docs/policy.md). Inputs and outputs stay float32.
 */
#ifndef COVEY_SAFETY_DOUBLE
#define COVEY_SAFETY_DOUBLE 1
#endif
#if COVEY_SAFETY_DOUBLE
typedef double covey_real_t;
#else
typedef float covey_real_t;
#endif

/* One ORCA half-plane: velocities v with det(dir, point - v) <= 0 are allowed. */
typedef struct {
    covey_real_t point[2];
    covey_real_t dir[2];
} covey_halfplane_t;

/* Most hard lines (keep-out zone edges, covey_zones.h) one call takes before the neighbours'. */
#define COVEY_SAFETY_MAX_HARD_LINES 32

/* Caller-owned working memory (7 KB at COVEY_MAX_INPUTS = 64 in double). */
typedef struct {
    /* + 2: the escape speed's track line (NC_ESCAPE_SPEED_FACTOR) and the ahead line */
    covey_halfplane_t lines[COVEY_MAX_INPUTS + COVEY_SAFETY_MAX_HARD_LINES + 2];
    covey_halfplane_t proj[COVEY_MAX_INPUTS + COVEY_SAFETY_MAX_HARD_LINES + 2]; /* the fallback's */
    covey_halfplane_t hard[COVEY_SAFETY_MAX_HARD_LINES]; /* covey_safety_filter_hard's input */
} covey_safety_scratch_t;

/* Result of one filter call. */
typedef struct {
    float vel_n_m_s;     /* filtered velocity, |v| <= max_speed_m_s (up to NC_ESCAPE_SPEED_FACTOR
                          * times that while a faster non-cooperative track adds a line); zero on
                          * a fault */
    float vel_e_m_s;
    int32_t n_lines;     /* neighbours within reach: r (1 + margin) + 2 max_speed time_horizon */
    int32_t changed;     /* 1: the preferred velocity (speed-clipped) broke a half-plane */
    int32_t infeasible;  /* 1: no velocity met every half-plane; the worst violation was minimised */
} covey_safety_out_t;

/* The defaults of policy/safety.py for a separation and a speed. */
covey_safety_config_t covey_safety_defaults(float separation_m, float max_speed_m_s);

/* Checks a filter configuration: NULL, then non-finite, then the ranges above. */
covey_status_t covey_safety_config_check(const covey_safety_config_t *cfg);

/* Checks one track: NULL, then non-finite (any of the four fields or pos_sigma_m), then
 * |pos| <= COVEY_MAX_ABS_POS_M, |vel| <= COVEY_MAX_ABS_VEL_M_S, pos_sigma_m in
 * [0, COVEY_SAFETY_MAX_SIGMA_M]. */
covey_status_t covey_track_check(const covey_track_t *t);

/*
 * Filters pref_vel (north, east) of `own` against n_nbrs neighbours.
 * Checks, first failure returned: NULL pointers (nbrs may be NULL when n_nbrs
 * == 0), the config, n_nbrs in [0, COVEY_MAX_INPUTS], own, pref_vel, each
 * neighbour in index order (non-finite before range). The caller drops stale
 * neighbours first (covey_traffic_prune).
 */
covey_status_t covey_safety_filter(const covey_safety_config_t *cfg, const covey_track_t *own,
                                   const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                   int32_t n_nbrs, covey_safety_scratch_t *scratch,
                                   covey_safety_out_t *out);

/*
 * covey_safety_filter with n_hard hard lines in scratch->hard (keep-out zones: covey_zones.c
 * covey_safety_filter_zones fills them): they go first and are never relaxed; when the
 * neighbours' lines cannot all be met, their worst violation is minimised inside the hard ones
 * (RVO2's obstacle lines; policy/safety.py solve_lines). n_hard in [0,
 * COVEY_SAFETY_MAX_HARD_LINES], else COVEY_ERR_RANGE; out->n_lines counts both kinds.
 */
covey_status_t covey_safety_filter_hard(const covey_safety_config_t *cfg, const covey_track_t *own,
                                        const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                        int32_t n_nbrs, int32_t n_hard,
                                        covey_safety_scratch_t *scratch, covey_safety_out_t *out);

/* sizeof(covey_safety_scratch_t), for bindings (ctypes). */
uint32_t covey_safety_scratch_bytes(void);

#ifdef __cplusplus
}
#endif

#endif /* COVEY_SAFETY_H */
