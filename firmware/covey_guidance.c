/*
 * covey_guidance.c - decision hold + separation filter; see covey_guidance.h.
 */
#include "covey_guidance.h"

#include <math.h>
#include <stddef.h>

#ifndef COVEY_W_DT
#define COVEY_W_DT 1.0f /* weights exported before the header carried dt */
#endif

float covey_trained_period_s(const covey_config_t *cfg)
{
    if (cfg == NULL || covey_config_check(cfg) != COVEY_OK) {
        return 0.0f;
    }
    /* 1 policy unit of time = (separation / 3) / cruise seconds */
    return COVEY_W_DT * (cfg->separation_m / 3.0f) / cfg->cruise_speed_m_s;
}

float covey_told_separation_m(float separation_m, int32_t safety_filter, float asked_m)
{
    if (asked_m != 0.0f) {
        return asked_m;
    }
    return safety_filter ? separation_m * COVEY_FILTERED_BERTH_SHARE : separation_m;
}

float covey_told_scale(const covey_safety_config_t *safety, float free_m, float own_pos_sigma_m,
                       const float *nbr_pos_sigma_m, const uint8_t *nbr_non_cooperative,
                       int32_t n)
{
    if (safety == NULL || !(free_m >= 0.0f)) {
        return 1.0f;
    }
    float worst = 0.0f;
    for (int32_t i = 0; nbr_pos_sigma_m != NULL && i < n; ++i) {
        if (nbr_non_cooperative == NULL || nbr_non_cooperative[i] == 0u) {
            worst = fmaxf(worst, nbr_pos_sigma_m[i]); /* fmaxf drops a NaN */
        }
    }
    const float x_own = fmaxf(own_pos_sigma_m - free_m, 0.0f);
    const float x_nbr = fmaxf(worst - free_m, 0.0f);
    return 1.0f + safety->sigma_k * sqrtf(x_own * x_own + x_nbr * x_nbr) / safety->radius_m;
}

covey_guidance_config_t covey_guidance_defaults(const covey_config_t *policy)
{
    covey_guidance_config_t g;
    g.policy = *policy;
    g.safety = covey_safety_defaults(policy->separation_m, policy->cruise_speed_m_s);
    g.decision_period_s = covey_trained_period_s(policy);
    g.safety_filter = 1;
    g.sparse_rule = 1;
    g.told_sigma_free_m = COVEY_TOLD_SIGMA_FREE_M;
    return g;
}

/* A goal or a velocity as covey_track_check checks a track: non-finite first, then range. */
static covey_status_t check2(float a, float b, float bound)
{
    if (!isfinite(a) || !isfinite(b)) {
        return COVEY_ERR_NONFINITE;
    }
    return (fabsf(a) <= bound && fabsf(b) <= bound) ? COVEY_OK : COVEY_ERR_RANGE;
}

covey_status_t covey_sparse_choose(const covey_safety_config_t *safety, const covey_track_t *own,
                                   const covey_goal_t *goal, const float policy_vel_m_s[2],
                                   const covey_track_t *nbrs, int32_t n_nbrs,
                                   covey_safety_scratch_t *scratch, covey_sparse_out_t *out)
{
    if (out != NULL) {
        out->vel_n_m_s = 0.0f;
        out->vel_e_m_s = 0.0f;
        out->straight = 0;
        out->n_encounters = 0;
    }
    if (safety == NULL || own == NULL || goal == NULL || policy_vel_m_s == NULL ||
        scratch == NULL || out == NULL || (nbrs == NULL && n_nbrs > 0)) {
        return COVEY_ERR_NULL;
    }
    covey_status_t st = covey_safety_config_check(safety);
    if (st != COVEY_OK) {
        return st;
    }
    if (n_nbrs < 0 || n_nbrs > COVEY_MAX_INPUTS) {
        return COVEY_ERR_RANGE;
    }
    st = covey_track_check(own);
    if (st == COVEY_OK) {
        st = check2(goal->pos_n_m, goal->pos_e_m, COVEY_MAX_ABS_POS_M);
    }
    if (st == COVEY_OK) {
        st = check2(policy_vel_m_s[0], policy_vel_m_s[1], COVEY_MAX_ABS_VEL_M_S);
    }
    for (int32_t i = 0; st == COVEY_OK && i < n_nbrs; ++i) {
        st = covey_track_check(&nbrs[i]);
    }
    if (st != COVEY_OK) {
        return st;
    }
    const float sep = safety->radius_m;
    const float cruise = safety->max_speed_m_s;
    const float period = COVEY_W_DT * (sep / 3.0f) / cruise;
    /* straight at the goal at cruise speed, slowed to reach it within one period */
    const float dn = goal->pos_n_m - own->pos_n_m;
    const float de = goal->pos_e_m - own->pos_e_m;
    const float dist = sqrtf(dn * dn + de * de);
    /* |vs| = dist x gain = min(cruise, dist / period), down to 0 on the goal */
    const float gain = fminf(cruise / fmaxf(dist, 1e-9f), 1.0f / period);
    const float vs[2] = {dn * gain, de * gain};
    /* goal_taken: a neighbour within one separation of the goal now */
    int32_t taken = 0;
    for (int32_t i = 0; i < n_nbrs && !taken; ++i) {
        const float tn = nbrs[i].pos_n_m - goal->pos_n_m;
        const float te = nbrs[i].pos_e_m - goal->pos_e_m;
        taken = sqrtf(tn * tn + te * te) < sep;
    }
    /* encounters only until vs reaches the goal, max(dist / cruise, period), unless it is
       taken (policy.sparse.encounter_horizon_s) */
    const float full = COVEY_SPARSE_HORIZON_PERIODS * period;
    const float horizon = taken ? full : fminf(full, fmaxf(dist / cruise, period));
    const float reach = COVEY_SPARSE_ENCOUNTER_SEPARATIONS * sep;
    const float clear = COVEY_SPARSE_CLEAR_SEPARATIONS * sep;
    /* a covey neighbour no faster than this stands (policy.sparse SparseConfig.still_speed_share):
       passed clear, outside the filter's berth for the pair, it is no encounter; nearer, it
       is one but never near now */
    const float still = COVEY_SPARSE_STILL_SHARE * cruise;
    const float base = sep * (1.0f + safety->margin);
    int32_t count = 0;
    float nearest = INFINITY;
    float now = INFINITY;
    for (int32_t i = 0; i < n_nbrs; ++i) {
        const float rpn = nbrs[i].pos_n_m - own->pos_n_m;
        const float rpe = nbrs[i].pos_e_m - own->pos_e_m;
        const float rvn = nbrs[i].vel_n_m_s - vs[0];
        const float rve = nbrs[i].vel_e_m_s - vs[1];
        const float vv = rvn * rvn + rve * rve;
        const float t = fminf(fmaxf(-(rpn * rvn + rpe * rve) / fmaxf(vv, 1e-12f), 0.0f), horizon);
        const float cn = rpn + rvn * t;
        const float ce = rpe + rve * t;
        const float d = sqrtf(cn * cn + ce * ce);
        const float sn = nbrs[i].vel_n_m_s;
        const float se = nbrs[i].vel_e_m_s;
        const int32_t standing =
            still > 0.0f && nbrs[i].non_cooperative == 0u && sn * sn + se * se <= still * still;
        if (!standing) {
            now = fminf(now, sqrtf(rpn * rpn + rpe * rpe));
        } else {
            const float so = own->pos_sigma_m;
            const float sj = nbrs[i].pos_sigma_m;
            if (d >= base + safety->sigma_k * sqrtf(so * so + sj * sj)) {
                continue;
            }
        }
        if (d < reach) {
            ++count;
            nearest = fminf(nearest, d);
        }
    }
    out->n_encounters = count;
    /* already flying along vs (within acos COVEY_SPARSE_ALIGNED_COS) */
    const float along = own->vel_n_m_s * vs[0] + own->vel_e_m_s * vs[1];
    const float own_sq = own->vel_n_m_s * own->vel_n_m_s + own->vel_e_m_s * own->vel_e_m_s;
    const float vs_sq = vs[0] * vs[0] + vs[1] * vs[1];
    const int32_t aligned =
        (along > 0.0f) &&
        (along * along >= COVEY_SPARSE_ALIGNED_COS * COVEY_SPARSE_ALIGNED_COS * own_sq * vs_sq);
    int32_t straight = (count <= COVEY_SPARSE_MAX_ENCOUNTERS) &&
                       (nearest >= COVEY_SPARSE_DEAD_ON_SEPARATIONS * sep) &&
                       ((now >= clear) || aligned);
    if (straight) {
        covey_safety_out_t f;
        st = covey_safety_filter(safety, own, vs, nbrs, n_nbrs, scratch, &f);
        if (st != COVEY_OK) {
            return st;
        }
        /* (f . vs / |vs|) >= share |vs|, without dividing: on the goal vs = 0 passes */
        straight = (f.vel_n_m_s * vs[0] + f.vel_e_m_s * vs[1]) >=
                   COVEY_SPARSE_PROGRESS_SHARE * (vs[0] * vs[0] + vs[1] * vs[1]);
    }
    out->straight = straight;
    out->vel_n_m_s = straight ? vs[0] : policy_vel_m_s[0];
    out->vel_e_m_s = straight ? vs[1] : policy_vel_m_s[1];
    return COVEY_OK;
}

void covey_hold_reset(covey_hold_t *hold)
{
    if (hold != NULL) {
        hold->vel_n_m_s = 0.0f;
        hold->vel_e_m_s = 0.0f;
        hold->goal.pos_n_m = 0.0f;
        hold->goal.pos_e_m = 0.0f;
        hold->decided_us = 0u;
        hold->valid = 0;
    }
}

int32_t covey_hold_due(const covey_hold_t *hold, const covey_goal_t *goal, uint64_t now_us,
                       float decision_period_s)
{
    if (hold == NULL || goal == NULL || !hold->valid) {
        return 1;
    }
    if (hold->goal.pos_n_m != goal->pos_n_m || hold->goal.pos_e_m != goal->pos_e_m) {
        return 1;
    }
    if (now_us < hold->decided_us) {
        return 1;
    }
    /* now - decided >= share * period, in microseconds (period <= 10 s: exact in float) */
    const float due_us = COVEY_DECISION_DUE_SHARE * decision_period_s * 1.0e6f;
    return ((float)(now_us - hold->decided_us) >= due_us) ? 1 : 0;
}

static covey_status_t fail(covey_hold_t *hold, covey_guidance_out_t *out, covey_status_t status)
{
    covey_hold_reset(hold);
    if (out != NULL) {
        out->vel_n_m_s = 0.0f;
        out->vel_e_m_s = 0.0f;
    }
    return status;
}

covey_status_t covey_guidance_step(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                   const covey_vehicle_t *own, const float own_vel_m_s[2],
                                   const covey_goal_t *goal, const covey_vehicle_t *nbrs,
                                   const float *nbr_vel_m_s, int32_t n_nbrs, uint64_t now_us,
                                   covey_guidance_scratch_t *scratch, covey_guidance_out_t *out)
{
    return covey_guidance_step_sky(cfg, hold, own, own_vel_m_s, 0.0f, goal, nbrs, nbr_vel_m_s,
                                   NULL, NULL, n_nbrs, now_us, scratch, out);
}

covey_status_t covey_guidance_step_sky(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                       const covey_vehicle_t *own, const float own_vel_m_s[2],
                                       float own_pos_sigma_m, const covey_goal_t *goal,
                                       const covey_vehicle_t *nbrs, const float *nbr_vel_m_s,
                                       const float *nbr_pos_sigma_m,
                                       const uint8_t *nbr_non_cooperative, int32_t n_nbrs,
                                       uint64_t now_us, covey_guidance_scratch_t *scratch,
                                       covey_guidance_out_t *out)
{
    return covey_guidance_step_zones(cfg, hold, own, own_vel_m_s, own_pos_sigma_m, goal, nbrs,
                                     nbr_vel_m_s, nbr_pos_sigma_m, nbr_non_cooperative, n_nbrs,
                                     NULL, now_us, scratch, out);
}

covey_status_t covey_guidance_step_zones(const covey_guidance_config_t *cfg, covey_hold_t *hold,
                                         const covey_vehicle_t *own, const float own_vel_m_s[2],
                                         float own_pos_sigma_m, const covey_goal_t *goal,
                                         const covey_vehicle_t *nbrs, const float *nbr_vel_m_s,
                                         const float *nbr_pos_sigma_m,
                                         const uint8_t *nbr_non_cooperative, int32_t n_nbrs,
                                         const covey_zones_t *zones, uint64_t now_us,
                                         covey_guidance_scratch_t *scratch,
                                         covey_guidance_out_t *out)
{
    if (out != NULL) {
        out->decided = 0;
        out->straight = 0;
        out->filter.n_lines = 0;
        out->filter.changed = 0;
        out->filter.infeasible = 0;
        out->command.n_used = 0;
        out->command.n_stale = 0;
        out->command.n_far = 0;
        out->command.n_excess = 0;
    }
    if (cfg == NULL || hold == NULL || own == NULL || own_vel_m_s == NULL || goal == NULL ||
        scratch == NULL || out == NULL || (nbrs == NULL && n_nbrs > 0) ||
        (cfg->safety_filter && nbr_vel_m_s == NULL && n_nbrs > 0)) {
        return fail(hold, out, COVEY_ERR_NULL);
    }
    covey_status_t st = covey_config_check(&cfg->policy);
    if (st == COVEY_OK && cfg->safety_filter) {
        st = covey_safety_config_check(&cfg->safety);
    }
    if (st == COVEY_OK && !isfinite(cfg->decision_period_s)) {
        st = COVEY_ERR_NONFINITE;
    }
    if (st == COVEY_OK && !(cfg->decision_period_s >= 0.0f &&
                            cfg->decision_period_s <= COVEY_MAX_DECISION_PERIOD_S)) {
        st = COVEY_ERR_RANGE;
    }
    if (st != COVEY_OK) {
        return fail(hold, out, st);
    }

    if (covey_hold_due(hold, goal, now_us, cfg->decision_period_s)) {
        /* GNSS worse than the preset: the policy is told the berth the filter keeps grow */
        covey_config_t told = cfg->policy;
        told.separation_m *= covey_told_scale(&cfg->safety, cfg->told_sigma_free_m,
                                              own_pos_sigma_m, nbr_pos_sigma_m,
                                              nbr_non_cooperative, n_nbrs);
        st = covey_command(&told, own, goal, nbrs, n_nbrs, now_us, &scratch->policy,
                           &out->command);
        if (st != COVEY_OK) {
            return fail(hold, out, st);
        }
        hold->vel_n_m_s = out->command.vel_n_m_s;
        hold->vel_e_m_s = out->command.vel_e_m_s;
        hold->goal = *goal;
        hold->decided_us = now_us;
        hold->valid = 1;
        out->decided = 1;
    } else {
        /* between decisions the own state is still checked: a held command never outlives it */
        if (own->stamp_us > now_us) {
            return fail(hold, out, COVEY_ERR_RANGE);
        }
        if (now_us - own->stamp_us > cfg->policy.max_own_age_us) {
            return fail(hold, out, COVEY_ERR_STALE);
        }
    }

    if (!cfg->safety_filter) {
        out->vel_n_m_s = hold->vel_n_m_s;
        out->vel_e_m_s = hold->vel_e_m_s;
        return COVEY_OK;
    }
    if (n_nbrs < 0 || n_nbrs > COVEY_MAX_INPUTS) {
        return fail(hold, out, COVEY_ERR_RANGE);
    }
    int32_t n_tracks = 0;
    for (int32_t i = 0; i < n_nbrs; ++i) {
        if (nbrs[i].stamp_us > now_us) {
            return fail(hold, out, COVEY_ERR_RANGE);
        }
        if (now_us - nbrs[i].stamp_us > cfg->policy.max_neighbour_age_us) {
            continue;
        }
        covey_track_t *t = &scratch->tracks[n_tracks++];
        t->pos_n_m = nbrs[i].pos_n_m;
        t->pos_e_m = nbrs[i].pos_e_m;
        t->vel_n_m_s = nbr_vel_m_s[2 * i];
        t->vel_e_m_s = nbr_vel_m_s[2 * i + 1];
        t->id = 0u; /* the tick takes no ids yet: coincident neighbours are not untied here */
        t->pos_sigma_m = nbr_pos_sigma_m != NULL ? nbr_pos_sigma_m[i] : 0.0f;
        /* the kind as given (COVEY_TRACK_*): a manned aircraft keeps its own berth */
        t->non_cooperative = nbr_non_cooperative != NULL ? nbr_non_cooperative[i] : 0u;
    }
    const covey_track_t me = {own->pos_n_m,  own->pos_e_m, own_vel_m_s[0],
                              own_vel_m_s[1], 0u,           own_pos_sigma_m,
                              0u};
    if (out->decided && cfg->sparse_rule) {
        covey_sparse_out_t sparse;
        const float asked[2] = {hold->vel_n_m_s, hold->vel_e_m_s};
        st = covey_sparse_choose(&cfg->safety, &me, goal, asked, scratch->tracks, n_tracks,
                                 &scratch->safety, &sparse);
        if (st != COVEY_OK) {
            return fail(hold, out, st);
        }
        hold->vel_n_m_s = sparse.vel_n_m_s;
        hold->vel_e_m_s = sparse.vel_e_m_s;
        out->straight = sparse.straight;
    }
    const float pref[2] = {hold->vel_n_m_s, hold->vel_e_m_s};
    /* zones NULL or empty: exactly covey_safety_filter */
    st = covey_safety_filter_zones(&cfg->safety, zones, &me, pref, scratch->tracks, n_tracks,
                                   &scratch->safety, &out->filter);
    if (st != COVEY_OK) {
        return fail(hold, out, st);
    }
    out->vel_n_m_s = out->filter.vel_n_m_s;
    out->vel_e_m_s = out->filter.vel_e_m_s;
    return COVEY_OK;
}

uint32_t covey_guidance_scratch_bytes(void)
{
    return (uint32_t)sizeof(covey_guidance_scratch_t);
}
