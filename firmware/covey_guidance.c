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

covey_guidance_config_t covey_guidance_defaults(const covey_config_t *policy)
{
    covey_guidance_config_t g;
    g.policy = *policy;
    g.safety = covey_safety_defaults(policy->separation_m, policy->cruise_speed_m_s);
    g.decision_period_s = covey_trained_period_s(policy);
    g.safety_filter = 1;
    return g;
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
    if (out != NULL) {
        out->decided = 0;
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
        st = covey_command(&cfg->policy, own, goal, nbrs, n_nbrs, now_us, &scratch->policy,
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
    }
    const covey_track_t me = {own->pos_n_m, own->pos_e_m, own_vel_m_s[0], own_vel_m_s[1]};
    const float pref[2] = {hold->vel_n_m_s, hold->vel_e_m_s};
    st = covey_safety_filter(&cfg->safety, &me, pref, scratch->tracks, n_tracks, &scratch->safety,
                             &out->filter);
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
