/*
 * covey_driver.c - line-oriented host driver of the policy core, for the
 * parity, sanitizer and fuzz tests (firmware/hostbuild.py builds it).
 *
 * stdin, one case per line, whitespace-separated tokens:
 *   C sep_m cruise_m_s max_nbr_age_us max_own_age_us max_nbrs
 *     own_n own_e own_h own_stamp_us goal_n goal_e now_us n_nbrs n_rec
 *     [n e h stamp_us] * n_rec
 *   A n_steps n_values [value] * n_values      (seq then goal features)
 *   S radius_m margin horizon_s dt_s max_speed_m_s responsibility
 *     own_n own_e own_vn own_ve pref_n pref_e n_nbrs n_rec [n e vn ve] * n_rec
 *   P as S with goal_n goal_e after pref_e     (covey_sparse_choose; pref = the policy's)
 * stdout, one line per case:
 *   C: status vel_n vel_e a_fwd a_right n_used n_stale n_far n_excess
 *   A: status a_fwd a_right
 *   S: status vel_n vel_e n_lines changed infeasible
 *   P: status vel_n vel_e straight n_encounters
 * Floats are %.9g (exact for float32); "nan", "inf" parse with strtof.
 * n_nbrs is passed to the core as given (it may be negative or too large: the
 * core must say RANGE before touching the array); n_rec <= COVEY_MAX_INPUTS
 * records are read into a zero-filled array.
 */
#include "covey_guidance.h"
#include "covey_policy.h"
#include "covey_safety.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define MAX_VALUES (COVEY_MAX_NEIGHBOURS * COVEY_INPUT + COVEY_GOAL)

static int read_token(char *buf, size_t size)
{
    char fmt[16];
    snprintf(fmt, sizeof fmt, "%%%zus", size - 1);
    return scanf(fmt, buf) == 1;
}

static int read_f(float *x)
{
    char tok[64];
    if (!read_token(tok, sizeof tok)) {
        return 0;
    }
    *x = strtof(tok, NULL);
    return 1;
}

static int read_i64(long long *x)
{
    char tok[64];
    if (!read_token(tok, sizeof tok)) {
        return 0;
    }
    *x = strtoll(tok, NULL, 10);
    return 1;
}

static int read_u64(uint64_t *x)
{
    char tok[64];
    if (!read_token(tok, sizeof tok)) {
        return 0;
    }
    *x = (uint64_t)strtoull(tok, NULL, 10);
    return 1;
}

static int run_command_case(covey_scratch_t *scratch, covey_vehicle_t *nbrs)
{
    covey_config_t cfg;
    covey_vehicle_t own;
    covey_goal_t goal;
    uint64_t now_us;
    long long max_n, n_nbrs, n_rec;
    int ok = read_f(&cfg.separation_m) && read_f(&cfg.cruise_speed_m_s) &&
             read_u64(&cfg.max_neighbour_age_us) && read_u64(&cfg.max_own_age_us) &&
             read_i64(&max_n) && read_f(&own.pos_n_m) && read_f(&own.pos_e_m) &&
             read_f(&own.heading_rad) && read_u64(&own.stamp_us) && read_f(&goal.pos_n_m) &&
             read_f(&goal.pos_e_m) && read_u64(&now_us) && read_i64(&n_nbrs) && read_i64(&n_rec);
    if (!ok || n_rec < 0 || n_rec > COVEY_MAX_INPUTS) {
        return 0;
    }
    cfg.max_neighbours = (int32_t)max_n;
    memset(nbrs, 0, sizeof(covey_vehicle_t) * COVEY_MAX_INPUTS);
    for (long long i = 0; i < n_rec; ++i) {
        if (!(read_f(&nbrs[i].pos_n_m) && read_f(&nbrs[i].pos_e_m) &&
              read_f(&nbrs[i].heading_rad) && read_u64(&nbrs[i].stamp_us))) {
            return 0;
        }
    }
    covey_command_t out;
    covey_status_t st =
        covey_command(&cfg, &own, &goal, nbrs, (int32_t)n_nbrs, now_us, scratch, &out);
    printf("%d %.9g %.9g %.9g %.9g %d %d %d %d\n", (int)st, (double)out.vel_n_m_s,
           (double)out.vel_e_m_s, (double)out.action[0], (double)out.action[1], (int)out.n_used,
           (int)out.n_stale, (int)out.n_far, (int)out.n_excess);
    return 1;
}

static int run_action_case(covey_scratch_t *scratch, float *values)
{
    long long n_steps, n_values;
    if (!(read_i64(&n_steps) && read_i64(&n_values)) || n_values < 0 || n_values > MAX_VALUES) {
        return 0;
    }
    for (long long k = 0; k < n_values; ++k) {
        if (!read_f(&values[k])) {
            return 0;
        }
    }
    float action[2];
    /* the goal features follow the sequence; for a bad n_steps point them anywhere valid */
    long long goal_at = n_steps * COVEY_INPUT;
    if (goal_at < 0 || goal_at + COVEY_GOAL > n_values) {
        goal_at = 0;
    }
    covey_status_t st = covey_action(values, (int32_t)n_steps, values + goal_at, scratch, action);
    printf("%d %.9g %.9g\n", (int)st, (double)action[0], (double)action[1]);
    return 1;
}

/* "S" (the filter) and "P" (the sparse rule, with a goal after the preference) cases. */
static int run_safety_case(covey_safety_scratch_t *scratch, covey_track_t *tracks, int sparse)
{
    covey_safety_config_t cfg;
    covey_track_t own = {0.0f, 0.0f, 0.0f, 0.0f, 0u, 0.0f, 0u}; /* no ids, sigmas or traffic */
    float pref[2];
    covey_goal_t goal = {0.0f, 0.0f};
    long long n_nbrs, n_rec;
    int ok = read_f(&cfg.radius_m) && read_f(&cfg.margin) && read_f(&cfg.time_horizon_s) &&
             read_f(&cfg.dt_s) && read_f(&cfg.max_speed_m_s) && read_f(&cfg.responsibility) &&
             read_f(&own.pos_n_m) && read_f(&own.pos_e_m) && read_f(&own.vel_n_m_s) &&
             read_f(&own.vel_e_m_s) && read_f(&pref[0]) && read_f(&pref[1]) &&
             (!sparse || (read_f(&goal.pos_n_m) && read_f(&goal.pos_e_m))) &&
             read_i64(&n_nbrs) && read_i64(&n_rec);
    if (!ok || n_rec < 0 || n_rec > COVEY_MAX_INPUTS) {
        return 0;
    }
    cfg.sigma_k = 0.0f; /* the "S" lines carry no uncertainty (tests/test_safety_sky.py: ctypes) */
    cfg.non_cooperative_radius_m = 0.0f;
    cfg.manned_radius_m = 0.0f;
    cfg.recover_speed_share = COVEY_SAFETY_RECOVER_SPEED_SHARE; /* SafetyConfig's default */
    memset(tracks, 0, sizeof(covey_track_t) * COVEY_MAX_INPUTS);
    for (long long i = 0; i < n_rec; ++i) {
        if (!(read_f(&tracks[i].pos_n_m) && read_f(&tracks[i].pos_e_m) &&
              read_f(&tracks[i].vel_n_m_s) && read_f(&tracks[i].vel_e_m_s))) {
            return 0;
        }
    }
    if (sparse) {
        covey_sparse_out_t so;
        covey_status_t st = covey_sparse_choose(&cfg, &own, &goal, pref, tracks, (int32_t)n_nbrs,
                                                scratch, &so);
        printf("%d %.9g %.9g %d %d\n", (int)st, (double)so.vel_n_m_s, (double)so.vel_e_m_s,
               (int)so.straight, (int)so.n_encounters);
        return 1;
    }
    covey_safety_out_t out;
    covey_status_t st =
        covey_safety_filter(&cfg, &own, pref, tracks, (int32_t)n_nbrs, scratch, &out);
    printf("%d %.9g %.9g %d %d %d\n", (int)st, (double)out.vel_n_m_s, (double)out.vel_e_m_s,
           (int)out.n_lines, (int)out.changed, (int)out.infeasible);
    return 1;
}

int main(void)
{
    static covey_scratch_t scratch;
    static covey_vehicle_t nbrs[COVEY_MAX_INPUTS];
    static float values[MAX_VALUES];
    static covey_safety_scratch_t safety_scratch;
    static covey_track_t tracks[COVEY_MAX_INPUTS];
    char kind[8];
    while (read_token(kind, sizeof kind)) {
        int ok = 0;
        if (strcmp(kind, "C") == 0) {
            ok = run_command_case(&scratch, nbrs);
        } else if (strcmp(kind, "A") == 0) {
            ok = run_action_case(&scratch, values);
        } else if (strcmp(kind, "S") == 0) {
            ok = run_safety_case(&safety_scratch, tracks, 0);
        } else if (strcmp(kind, "P") == 0) {
            ok = run_safety_case(&safety_scratch, tracks, 1);
        }
        if (!ok) {
            fprintf(stderr, "covey_driver: malformed case\n");
            return 2;
        }
    }
    return 0;
}
