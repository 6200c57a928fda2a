/*
 * covey_traffic.c - neighbour table and heading bookkeeping; see covey_traffic.h.
 */
#include "covey_traffic.h"

#include <math.h>
#include <stddef.h>

void covey_traffic_init(covey_traffic_t *t)
{
    if (t != NULL) {
        t->n = 0;
    }
}

static covey_status_t check_report(const covey_vehicle_t *v)
{
    if (!isfinite(v->pos_n_m) || !isfinite(v->pos_e_m) || !isfinite(v->heading_rad)) {
        return COVEY_ERR_NONFINITE;
    }
    if (fabsf(v->pos_n_m) > COVEY_MAX_ABS_POS_M || fabsf(v->pos_e_m) > COVEY_MAX_ABS_POS_M ||
        fabsf(v->heading_rad) > COVEY_MAX_ABS_HEADING_RAD) {
        return COVEY_ERR_RANGE;
    }
    return COVEY_OK;
}

int32_t covey_traffic_is_covey(uint32_t icao_address, const char *callsign, int32_t emitter_type)
{
    return (icao_address & COVEY_TRAFFIC_ICAO_MASK) == COVEY_TRAFFIC_ICAO_BASE &&
           callsign != NULL && callsign[0] == 'C' && callsign[1] == 'V' && callsign[2] == 'Y' &&
           emitter_type == COVEY_ADSB_EMITTER_UAV;
}

int32_t covey_emitter_is_manned(int32_t emitter_type)
{
    /* light 1 .. highly manoeuvrable 6, rotorcraft 7, glider 9, lighter than air 10,
     * parachute 11, ultralight 12 (8 and 13 are unassigned, 14 UAV, 15+ not aircraft) */
    return (emitter_type >= 1 && emitter_type <= 7) || (emitter_type >= 9 && emitter_type <= 12);
}

static void store(covey_traffic_t *t, int32_t i, uint32_t id, const covey_vehicle_t *report,
                  float vel_n_m_s, float vel_e_m_s, uint8_t non_cooperative, uint8_t manned)
{
    t->id[i] = id;
    t->report[i] = *report;
    t->vel_m_s[i][0] = vel_n_m_s;
    t->vel_m_s[i][1] = vel_e_m_s;
    t->non_cooperative[i] = non_cooperative;
    t->manned[i] = manned;
}

covey_status_t covey_traffic_put_track(covey_traffic_t *t, uint32_t id,
                                       const covey_vehicle_t *report, float vel_n_m_s,
                                       float vel_e_m_s)
{
    return covey_traffic_put_classified(t, id, report, vel_n_m_s, vel_e_m_s, 0, 0);
}

covey_status_t covey_traffic_put_classified(covey_traffic_t *t, uint32_t id,
                                            const covey_vehicle_t *report, float vel_n_m_s,
                                            float vel_e_m_s, int32_t non_cooperative,
                                            int32_t manned)
{
    const uint8_t nc = non_cooperative ? 1u : 0u;
    const uint8_t mn = manned ? 1u : 0u;
    if (t == NULL || report == NULL) {
        return COVEY_ERR_NULL;
    }
    if (t->n < 0 || t->n > COVEY_MAX_INPUTS) {
        return COVEY_ERR_RANGE; /* corrupt table */
    }
    covey_status_t st = check_report(report);
    if (st != COVEY_OK) {
        return st;
    }
    if (!isfinite(vel_n_m_s) || !isfinite(vel_e_m_s)) {
        return COVEY_ERR_NONFINITE;
    }
    if (fabsf(vel_n_m_s) > COVEY_MAX_ABS_VEL_M_S || fabsf(vel_e_m_s) > COVEY_MAX_ABS_VEL_M_S) {
        return COVEY_ERR_RANGE;
    }
    int32_t oldest = 0;
    for (int32_t i = 0; i < t->n; ++i) {
        if (t->id[i] == id) {
            store(t, i, id, report, vel_n_m_s, vel_e_m_s, nc, mn);
            return COVEY_OK;
        }
        if (t->report[i].stamp_us < t->report[oldest].stamp_us) {
            oldest = i;
        }
    }
    if (t->n < COVEY_MAX_INPUTS) {
        store(t, t->n, id, report, vel_n_m_s, vel_e_m_s, nc, mn);
        t->n++;
    } else if (report->stamp_us > t->report[oldest].stamp_us) {
        store(t, oldest, id, report, vel_n_m_s, vel_e_m_s, nc, mn);
    }
    return COVEY_OK;
}

covey_status_t covey_traffic_put(covey_traffic_t *t, uint32_t id, const covey_vehicle_t *report)
{
    return covey_traffic_put_track(t, id, report, 0.0f, 0.0f);
}

int32_t covey_traffic_prune(covey_traffic_t *t, uint64_t now_us, uint64_t max_age_us)
{
    if (t == NULL || t->n < 0 || t->n > COVEY_MAX_INPUTS) {
        return 0;
    }
    int32_t kept = 0;
    for (int32_t i = 0; i < t->n; ++i) {
        const uint64_t stamp = t->report[i].stamp_us;
        if (stamp <= now_us && now_us - stamp <= max_age_us) {
            store(t, kept, t->id[i], &t->report[i], t->vel_m_s[i][0], t->vel_m_s[i][1],
                  t->non_cooperative[i], t->manned[i]);
            kept++;
        }
    }
    const int32_t removed = t->n - kept;
    t->n = kept;
    return removed;
}

int32_t covey_traffic_kinds(const covey_traffic_t *t, uint8_t *kinds)
{
    if (t == NULL || kinds == NULL || t->n < 0 || t->n > COVEY_MAX_INPUTS) {
        return 0;
    }
    for (int32_t i = 0; i < t->n; ++i) {
        kinds[i] = (uint8_t)(!t->non_cooperative[i] ? COVEY_TRACK_COOPERATIVE
                             : t->manned[i]        ? COVEY_TRACK_MANNED
                                                   : COVEY_TRACK_TRAFFIC);
    }
    return t->n;
}

float covey_heading_for_goal(covey_heading_t *h, float pos_n_m, float pos_e_m,
                             const covey_goal_t *goal)
{
    if (h == NULL || goal == NULL) {
        return 0.0f;
    }
    const int32_t new_goal = !h->valid || goal->pos_n_m != h->goal.pos_n_m ||
                             goal->pos_e_m != h->goal.pos_e_m;
    if (new_goal) {
        const float d_n = goal->pos_n_m - pos_n_m;
        const float d_e = goal->pos_e_m - pos_e_m;
        if (!h->valid) {
            h->heading_rad = 0.0f;
        }
        /* bearing to the goal; a goal within 1 mm (or a non-finite one) keeps the heading */
        if (isfinite(d_n) && isfinite(d_e) && d_n * d_n + d_e * d_e >= 1.0e-6f) {
            h->heading_rad = atan2f(d_e, d_n);
        }
        h->goal = *goal;
        h->valid = 1;
    }
    return h->heading_rad;
}

void covey_heading_after_command(covey_heading_t *h, const covey_command_t *cmd)
{
    if (h == NULL || cmd == NULL) {
        return;
    }
    const float v_n = cmd->vel_n_m_s;
    const float v_e = cmd->vel_e_m_s;
    if (isfinite(v_n) && isfinite(v_e) &&
        v_n * v_n + v_e * v_e >= COVEY_HEADING_MIN_SPEED_M_S * COVEY_HEADING_MIN_SPEED_M_S) {
        h->heading_rad = atan2f(v_e, v_n);
    }
}
