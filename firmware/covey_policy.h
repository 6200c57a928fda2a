/*
 * covey_policy.h - the onboard guidance policy of covey, in C99.
 *
 * Implements docs/POLICY_SPEC.md end to end: neighbour observation (both
 * encodings), sense-range drop, nearest-max selection, ordering, the LSTM
 * spatial encoder, the tanh head, unit clipping, the body -> NED rotation and
 * the scaling to metres and m/s.
 *
 * Rules of this core (what makes it safe to drop into an autopilot):
 *   - sizes are compile-time constants; the weights are const arrays from a
 *     generated header (firmware/export_c.py -> covey_weights.h);
 *   - no malloc, no mutable globals: configuration and scratch memory are
 *     owned by the caller and passed in;
 *   - float32 arithmetic only (single-precision FPU of a Cortex-M7);
 *   - the current time is passed in (microseconds, the PX4 hrt_abstime clock);
 *   - every input is checked (isfinite, then its range, then freshness) and
 *     faults come back as a covey_status_t, never as a trap.
 *
 * Frames and units: local horizontal frame, x = north, y = east, metres.
 * Heading: radians, 0 = north, positive clockwise.
 *
 * Selecting the weights header: by default "covey_weights.h" from the include
 * path; build with -DCOVEY_WEIGHTS_HEADER='"other.h"' to pick another one.
 */
#ifndef COVEY_POLICY_H
#define COVEY_POLICY_H

#include <stdint.h>

#ifndef COVEY_WEIGHTS_HEADER
#define COVEY_WEIGHTS_HEADER "covey_weights.h"
#endif
#include COVEY_WEIGHTS_HEADER

#ifdef __cplusplus
extern "C" {
#endif

/* ---- compile-time bounds ------------------------------------------------ */

/* Most neighbours fed to the LSTM (the nearest are kept). The paper flies 35. */
#ifndef COVEY_MAX_NEIGHBOURS
#define COVEY_MAX_NEIGHBOURS 40
#endif

/* Most neighbour reports one call may pass in (stale and far ones included). */
#ifndef COVEY_MAX_INPUTS
#define COVEY_MAX_INPUTS 64
#endif

/* Input ranges: beyond these a finite value is a fault (COVEY_ERR_RANGE). */
#define COVEY_MAX_ABS_POS_M 1.0e5f          /* 100 km local frame; float32 ulp 8 mm */
#define COVEY_MAX_ABS_HEADING_RAD 12.5663706f /* 4 pi: one unwrapped turn either way */
#define COVEY_MIN_SEPARATION_M 0.01f       /* keeps 3 / separation and distances finite */
#define COVEY_MAX_SEPARATION_M 1000.0f
#define COVEY_MIN_CRUISE_SPEED_M_S 0.01f
#define COVEY_MAX_CRUISE_SPEED_M_S 100.0f
#define COVEY_MAX_ABS_FEATURE 1.0e9f        /* covey_action inputs */

#if COVEY_MAX_NEIGHBOURS < 1 || COVEY_MAX_INPUTS < COVEY_MAX_NEIGHBOURS || COVEY_MAX_INPUTS > 32767
#error "need 1 <= COVEY_MAX_NEIGHBOURS <= COVEY_MAX_INPUTS <= 32767"
#endif

/* Network sizes, from the weights header. */
#define COVEY_INPUT COVEY_W_INPUT         /* X: width of one neighbour tuple */
#define COVEY_HIDDEN COVEY_W_HIDDEN       /* H: LSTM hidden size */
#define COVEY_GOAL COVEY_W_GOAL           /* G: width of the goal features */
#define COVEY_HEAD_MAX_WIDTH COVEY_W_HEAD_MAX_WIDTH

/* ---- faults --------------------------------------------------------------- */

/*
 * Checks run in this order and the first failure is returned:
 *   1. NULL pointers                      -> COVEY_ERR_NULL
 *   2. config: non-finite, out of range   -> COVEY_ERR_NONFINITE / COVEY_ERR_RANGE
 *   3. neighbour count outside [0, COVEY_MAX_INPUTS] -> COVEY_ERR_RANGE
 *   4. own state: non-finite, range, stamp in the future (range), too old (stale)
 *   5. goal: non-finite, range
 *   6. each neighbour in index order: stamp in the future (range); too old ->
 *      dropped without looking at its fields; else non-finite, range.
 * A stale neighbour slot is ignored whatever it holds, so one old garbage slot
 * cannot ground the vehicle; a fresh corrupt one does fault, because silently
 * ignoring a live neighbour could fly into it.
 * On any fault the command output is zero velocity (hover) with the status set;
 * the caller must still branch on the status.
 */
typedef enum {
    COVEY_OK = 0,
    COVEY_ERR_NULL = 1,      /* a required pointer is NULL */
    COVEY_ERR_NONFINITE = 2, /* NaN or +-inf in an input */
    COVEY_ERR_RANGE = 3,     /* finite but outside its documented range */
    COVEY_ERR_STALE = 4      /* own state older than max_own_age_us */
} covey_status_t;

/* ---- inputs and outputs ------------------------------------------------- */

/* Run-time configuration; check once with covey_config_check (every call rechecks). */
typedef struct {
    float separation_m;        /* [0.01, 1000]: 3 policy units of distance = this many metres */
    float cruise_speed_m_s;    /* [0.01, 100]: 1 policy unit of speed = this many m/s */
    uint64_t max_neighbour_age_us; /* older neighbour reports are dropped */
    uint64_t max_own_age_us;   /* older own state is a fault (COVEY_ERR_STALE) */
    int32_t max_neighbours;    /* [0, COVEY_MAX_NEIGHBOURS]: nearest kept */
} covey_config_t;

/* One vehicle's state as the guidance sees it (own vehicle or a neighbour). */
typedef struct {
    float pos_n_m;      /* north, metres, |.| <= COVEY_MAX_ABS_POS_M */
    float pos_e_m;      /* east, metres */
    float heading_rad;  /* 0 = north, clockwise, |.| <= COVEY_MAX_ABS_HEADING_RAD */
    uint64_t stamp_us;  /* when it was measured or received, on the caller's clock */
} covey_vehicle_t;

/* Goal position in the same local frame. */
typedef struct {
    float pos_n_m;
    float pos_e_m;
} covey_goal_t;

/* Result of one evaluation. */
typedef struct {
    float vel_n_m_s;     /* commanded velocity, north */
    float vel_e_m_s;     /* commanded velocity, east */
    float action[2];     /* clipped network action (forward, right), policy units */
    int32_t n_used;      /* neighbours fed to the LSTM */
    int32_t n_stale;     /* dropped: older than max_neighbour_age_us */
    int32_t n_far;       /* dropped: beyond the sense range */
    int32_t n_excess;    /* dropped: beyond max_neighbours (the farthest) */
} covey_command_t;

/* Caller-owned working memory (about 2 KB + 4 * COVEY_MAX_INPUTS * 2 bytes). */
typedef struct {
    float dist[COVEY_MAX_INPUTS];       /* policy-unit distance of each input */
    int16_t order[COVEY_MAX_INPUTS];    /* candidate indices, then feeding order */
    float seq[COVEY_MAX_NEIGHBOURS][COVEY_INPUT]; /* LSTM input sequence */
    float goal[COVEY_GOAL];             /* goal features */
    float gates[4 * COVEY_HIDDEN];      /* pre-activations i, f, g, o */
    float h[COVEY_HIDDEN];              /* LSTM hidden state */
    float c[COVEY_HIDDEN];              /* LSTM cell state */
    float z[2][COVEY_HEAD_MAX_WIDTH];   /* head activations, ping-pong */
} covey_scratch_t;

/* ---- API ------------------------------------------------------------------ */

/* Checks a configuration (step 2 above). */
covey_status_t covey_config_check(const covey_config_t *cfg);

/*
 * Full guidance step: observation -> network -> NED velocity in m/s.
 * nbrs may be NULL when n_nbrs == 0. out is always written when non-NULL.
 */
covey_status_t covey_command(const covey_config_t *cfg, const covey_vehicle_t *own,
                             const covey_goal_t *goal, const covey_vehicle_t *nbrs,
                             int32_t n_nbrs, uint64_t now_us, covey_scratch_t *scratch,
                             covey_command_t *out);

/*
 * Network only: seq is n_steps x COVEY_INPUT row-major (already encoded and
 * ordered), goal_feat is COVEY_GOAL values; action gets the clipped (fwd, right).
 * n_steps in [0, COVEY_MAX_NEIGHBOURS]; inputs finite and |.| <= COVEY_MAX_ABS_FEATURE.
 */
covey_status_t covey_action(const float *seq, int32_t n_steps, const float *goal_feat,
                            covey_scratch_t *scratch, float action[2]);

/* sizeof(covey_scratch_t), for bindings (ctypes) that allocate it as raw bytes. */
uint32_t covey_scratch_bytes(void);

/* Short name of a status, for logs. */
const char *covey_status_name(covey_status_t status);

#ifdef __cplusplus
}
#endif

#endif /* COVEY_POLICY_H */
