/*
 * covey_guidance.h - one control tick of covey's onboard guidance, in C99:
 * the policy decides at its trained period, its velocity is held in between,
 * and the separation filter (covey_safety.h) runs on the held velocity at every
 * tick against the latest neighbours. This is what agent/guidance.py does in
 * the companion, so the PX4 module and the emulator's onboard mode fly the
 * same thing.
 *
 * Same rules as covey_policy.h: caller-owned state and scratch, no malloc,
 * float32, time passed in, faults as covey_status_t with a zero (hover) output.
 */
#ifndef COVEY_GUIDANCE_H
#define COVEY_GUIDANCE_H

#include "covey_safety.h"
#include "covey_zones.h"

#ifdef __cplusplus
extern "C" {
#endif

/* A decision is due once this share of the period has passed (agent/guidance.py
 * DECISION_DUE_SHARE): tick jitter must not push a decision a whole tick late. */
#define COVEY_DECISION_DUE_SHARE 0.95f
#define COVEY_MAX_DECISION_PERIOD_S 10.0f

typedef struct {
    covey_config_t policy;          /* the policy core's configuration */
    covey_safety_config_t safety;   /* the filter's (radius_m = policy.separation_m as a rule) */
    float decision_period_s;        /* [0, 10]: seconds between decisions; 0 = every tick */
    int32_t safety_filter;          /* 1: filter every tick; 0: the policy alone (the paper) */
    int32_t sparse_rule;            /* 1 (with the filter): covey_sparse_choose at each decision */
    float told_sigma_free_m;        /* >= 0: beyond this position 1-sigma the policy is told
                                       covey_told_scale times policy.separation_m; < 0: never */
} covey_guidance_config_t;

/* The held decision, owned by the caller; zero-initialise or covey_hold_reset. */
typedef struct {
    float vel_n_m_s;      /* the last decision's velocity */
    float vel_e_m_s;
    covey_goal_t goal;    /* the goal it was made for */
    uint64_t decided_us;  /* when */
    int32_t valid;        /* 0: nothing held, the next tick decides */
} covey_hold_t;

typedef struct {
    covey_scratch_t policy;
    covey_safety_scratch_t safety;
    covey_track_t tracks[COVEY_MAX_INPUTS]; /* fresh neighbours with velocities */
} covey_guidance_scratch_t;

typedef struct {
    float vel_n_m_s;            /* the velocity to fly (filtered); zero on a fault */
    float vel_e_m_s;
    int32_t decided;            /* 1: the policy ran this tick */
    covey_command_t command;    /* the policy's output when decided (else zero counts) */
    covey_safety_out_t filter;  /* the filter's result (n_lines = 0 when off) */
    int32_t straight;           /* 1: this tick decided, by the sparse rule, to fly straight */
} covey_guidance_out_t;

/*
 * The sparse-traffic rule, policy/sparse.py's twin with SparseConfig's defaults: where a
 * vehicle meets at most two others, not dead-on, and nobody is near yet (or it already flies
 * that way), it flies straight at its goal and leaves the encounter to the filter (ORCA);
 * else the policy. A covey neighbour slower than COVEY_SPARSE_STILL_SHARE of the cruise speed
 * stands: the line passing it outside the filter's berth for the pair, it is no encounter;
 * nearer, it is one but never near now. Time unit: the trained period at the separation kept,
 * COVEY_W_DT x (radius_m / 3) / max_speed_m_s.
 */
#define COVEY_SPARSE_HORIZON_PERIODS 10.0f      /* this far ahead, not past a goal nobody is at */
#define COVEY_SPARSE_ENCOUNTER_SEPARATIONS 2.0f /* closest approach nearer: an encounter */
#define COVEY_SPARSE_DEAD_ON_SEPARATIONS (1.0f / 6.0f) /* nearer still: dead-on, the policy */
#define COVEY_SPARSE_MAX_ENCOUNTERS 2           /* more at once: dense, the policy */
#define COVEY_SPARSE_PROGRESS_SHARE 0.5f        /* the filtered straight line must keep this */
#define COVEY_SPARSE_CLEAR_SEPARATIONS 2.0f     /* nobody nearer than this now, */
#define COVEY_SPARSE_ALIGNED_COS 0.9f           /* unless already flying along the line */
#define COVEY_SPARSE_STILL_SHARE 0.25f          /* a covey neighbour this slow stands: outside
                                                   its berth no encounter, never near now */

typedef struct {
    float vel_n_m_s;        /* the velocity to hold: straight or the policy's */
    float vel_e_m_s;
    int32_t straight;       /* 1: straight at the goal */
    int32_t n_encounters;   /* neighbours whose straight-line closest approach is an encounter */
} covey_sparse_out_t;

/*
 * The rule for `own` (position, velocity) bound for `goal`, whose policy asked for
 * policy_vel_m_s, against n_nbrs fresh neighbours with velocities; `safety` is the filter
 * flight keeps (radius_m the separation, max_speed_m_s the cruise speed). Checks, first
 * failure returned: NULL, the config, n_nbrs in [0, COVEY_MAX_INPUTS], then own, goal,
 * policy_vel_m_s and each neighbour in index order, each non-finite before out of range
 * (positions COVEY_MAX_ABS_POS_M, velocities COVEY_MAX_ABS_VEL_M_S). On a fault the output
 * is zero and not straight.
 */
covey_status_t covey_sparse_choose(const covey_safety_config_t *safety, const covey_track_t *own,
                                   const covey_goal_t *goal, const float policy_vel_m_s[2],
                                   const covey_track_t *nbrs, int32_t n_nbrs,
                                   covey_safety_scratch_t *scratch, covey_sparse_out_t *out);

/* With the filter on and no berth asked for, the policy is told this share of
 * the separation, the one its weights were trained for (their config's
 * filtered_told_share, exported into the weights header; policy/runtime.py
 * filtered_told_share, docs/policy.md). A header from before it: 1.25 / 3. */
#ifdef COVEY_W_FILTERED_TOLD_SHARE
#define COVEY_FILTERED_BERTH_SHARE COVEY_W_FILTERED_TOLD_SHARE
#else
#define COVEY_FILTERED_BERTH_SHARE (1.25f / 3.0f)
#endif

/* The separation to tell the policy (covey_config_t.separation_m) while the
 * filter keeps separation_m: asked_m unless it is 0; for 0, separation_m x
 * COVEY_FILTERED_BERTH_SHARE with the filter on and separation_m with it off
 * (alone, the policy keeps the separation itself). Anything else asked (NaN,
 * negative) is passed on for covey_config_check to refuse. The twin of
 * policy/runtime.py told_separation_m (None there = 0 here). */
float covey_told_separation_m(float separation_m, int32_t safety_filter, float asked_m);

/* covey_guidance_defaults' told_sigma_free_m: the realistic preset's GNSS 1-sigma
 * (policy/runtime.py TOLD_SIGMA_FREE_M). */
#define COVEY_TOLD_SIGMA_FREE_M 0.5f

/* How many times its separation the policy is told at a decision (>= 1):
 * 1 + sigma_k hypot(x_own, x_nbr) / radius_m, x = max(0, sigma - free_m), with
 * own_pos_sigma_m and the largest of the n nbr_pos_sigma_m (NULL: 0) of the
 * cooperative neighbours (nbr_non_cooperative[i] 0, or NULL: all); free_m < 0 or
 * NaN: 1. NaN sigmas count as 0 (the filter refuses them). The twin of
 * policy/runtime.py told_scale with Sky.nbr_sigma_max_m. */
float covey_told_scale(const covey_safety_config_t *safety, float free_m, float own_pos_sigma_m,
                       const float *nbr_pos_sigma_m, const uint8_t *nbr_non_cooperative,
                       int32_t n);

/* The trained decision period in seconds: dt (1 policy unit of time, from the
 * weights header) times (separation / 3) / cruise speed. */
float covey_trained_period_s(const covey_config_t *cfg);

/* The default guidance config: trained period, filter on, policy/safety.py defaults. */
covey_guidance_config_t covey_guidance_defaults(const covey_config_t *policy);

void covey_hold_reset(covey_hold_t *hold);

/* 1 when a decision is due: nothing held, a new goal, the clock went back, or
 * now - decided >= COVEY_DECISION_DUE_SHARE * period. */
int32_t covey_hold_due(const covey_hold_t *hold, const covey_goal_t *goal, uint64_t now_us,
                       float decision_period_s);

/*
 * One tick. own_vel_m_s is (north, east); nbr_vel_m_s is n_nbrs x 2 row-major
 * (may be NULL when n_nbrs == 0 or the filter is off). Checks, first failure
 * returned: NULL, configs, decision_period_s; then the policy core's checks
 * when deciding (covey_policy.h), the own stamp every tick (future: RANGE,
 * older than max_own_age_us: STALE); then, with the filter on, neighbours
 * in index order (future stamp: RANGE; stale: dropped; fields checked by
 * covey_safety_filter). A fault forgets the held decision.
 */
covey_status_t covey_guidance_step(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                   const covey_vehicle_t *own, const float own_vel_m_s[2],
                                   const covey_goal_t *goal, const covey_vehicle_t *nbrs,
                                   const float *nbr_vel_m_s, int32_t n_nbrs, uint64_t now_us,
                                   covey_guidance_scratch_t *scratch, covey_guidance_out_t *out);

/*
 * covey_guidance_step with what the filter needs of real vehicles: own_pos_sigma_m, the own
 * position estimate's 1-sigma (metres, per axis), and per neighbour nbr_pos_sigma_m (n_nbrs,
 * or NULL: all 0) and nbr_non_cooperative (n_nbrs, the kind of each as covey_track_t carries it
 * (covey_safety.h): COVEY_TRACK_COOPERATIVE 0, COVEY_TRACK_TRAFFIC 1 (does not avoid),
 * COVEY_TRACK_MANNED 2 (does not avoid, kept manned_radius_m from; covey_traffic_kinds fills
 * this from the traffic table); NULL: all cooperative). covey_guidance_step is this with 0,
 * NULL, NULL. Checked by covey_safety_filter (non-finite, then [0, COVEY_SAFETY_MAX_SIGMA_M]).
 */
covey_status_t covey_guidance_step_sky(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                       const covey_vehicle_t *own, const float own_vel_m_s[2],
                                       float own_pos_sigma_m, const covey_goal_t *goal,
                                       const covey_vehicle_t *nbrs, const float *nbr_vel_m_s,
                                       const float *nbr_pos_sigma_m,
                                       const uint8_t *nbr_non_cooperative, int32_t n_nbrs,
                                       uint64_t now_us, covey_guidance_scratch_t *scratch,
                                       covey_guidance_out_t *out);

/*
 * covey_guidance_step_sky with keep-out zones (covey_zones_init, or covey_fence_zones from the
 * autopilot's geofence): the filter keeps every zone edge as a hard line (covey_zones.h), so
 * neither the policy nor traffic takes the vehicle into a zone. NULL or no vertices: exactly
 * covey_guidance_step_sky. The zones are not checked here (covey_zones_init did).
 */
covey_status_t covey_guidance_step_zones(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                         const covey_vehicle_t *own, const float own_vel_m_s[2],
                                         float own_pos_sigma_m, const covey_goal_t *goal,
                                         const covey_vehicle_t *nbrs, const float *nbr_vel_m_s,
                                         const float *nbr_pos_sigma_m,
                                         const uint8_t *nbr_non_cooperative, int32_t n_nbrs,
                                         const covey_zones_t *zones, uint64_t now_us,
                                         covey_guidance_scratch_t *scratch,
                                         covey_guidance_out_t *out);

/* sizeof(covey_guidance_scratch_t), for bindings (ctypes). */
uint32_t covey_guidance_scratch_bytes(void);

#ifdef __cplusplus
}
#endif

#endif /* COVEY_GUIDANCE_H */
