/*
 * covey_unit.c - host unit tests of covey_traffic.c and of the core's edge
 * cases that the random parity cases cannot reach (NULL pointers, ties,
 * +-pi wrap). Prints "covey_unit: <n> checks passed"; exits 1 on a failure.
 */
#include "covey_guidance.h"
#include "covey_traffic.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static int checks, failures;

#define CHECK(cond)                                                               \
    do {                                                                          \
        ++checks;                                                                 \
        if (!(cond)) {                                                            \
            ++failures;                                                           \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond); \
        }                                                                         \
    } while (0)

static covey_vehicle_t veh(float n, float e, float h, uint64_t stamp)
{
    covey_vehicle_t v = {n, e, h, stamp};
    return v;
}

static void test_traffic(void)
{
    static covey_traffic_t t;
    covey_traffic_init(&t);
    covey_vehicle_t a = veh(1.0f, 2.0f, 0.5f, 100u);
    CHECK(covey_traffic_put(&t, 7u, &a) == COVEY_OK && t.n == 1);
    a.pos_n_m = 3.0f;
    a.stamp_us = 200u;
    CHECK(covey_traffic_put(&t, 7u, &a) == COVEY_OK && t.n == 1 && t.report[0].pos_n_m == 3.0f);
    covey_vehicle_t bad = veh(NAN, 0.0f, 0.0f, 300u);
    CHECK(covey_traffic_put(&t, 7u, &bad) == COVEY_ERR_NONFINITE && t.report[0].stamp_us == 200u);
    bad = veh(0.0f, 2.0e5f, 0.0f, 300u);
    CHECK(covey_traffic_put(&t, 8u, &bad) == COVEY_ERR_RANGE && t.n == 1);
    CHECK(covey_traffic_put(NULL, 8u, &a) == COVEY_ERR_NULL);
    CHECK(covey_traffic_put(&t, 8u, NULL) == COVEY_ERR_NULL);

    /* fill the table; stamps 1000 + i, so entry id 7 (stamp 200) is the oldest */
    for (uint32_t i = 1; i < COVEY_MAX_INPUTS; ++i) {
        covey_vehicle_t v = veh((float)i, 0.0f, 0.0f, 1000u + i);
        CHECK(covey_traffic_put(&t, 100u + i, &v) == COVEY_OK);
    }
    CHECK(t.n == COVEY_MAX_INPUTS);
    covey_vehicle_t newer = veh(-5.0f, 0.0f, 0.0f, 5000u);
    CHECK(covey_traffic_put(&t, 999u, &newer) == COVEY_OK && t.n == COVEY_MAX_INPUTS);
    CHECK(t.id[0] == 999u && t.report[0].pos_n_m == -5.0f); /* replaced id 7 */
    covey_vehicle_t older = veh(-6.0f, 0.0f, 0.0f, 10u);
    CHECK(covey_traffic_put(&t, 555u, &older) == COVEY_OK);
    for (int32_t i = 0; i < t.n; ++i) {
        CHECK(t.id[i] != 555u); /* older than everything: not stored */
    }

    /* prune: keep stamps within 500 us of now = 1500 -> stamps 1001..1063 and 5000 is future */
    int32_t removed = covey_traffic_prune(&t, 1500u, 500u);
    CHECK(removed == 1 && t.n == COVEY_MAX_INPUTS - 1);
    removed = covey_traffic_prune(&t, 1540u, 500u); /* drops stamps < 1040 */
    CHECK(removed == 39 && t.n == COVEY_MAX_INPUTS - 40);
    CHECK(t.id[0] == 140u); /* order kept */

    /* velocities travel with their reports (put_track, replace, prune) */
    covey_traffic_init(&t);
    covey_vehicle_t b = veh(1.0f, 1.0f, 0.0f, 10u);
    CHECK(covey_traffic_put_track(&t, 1u, &b, 0.5f, -0.25f) == COVEY_OK);
    b.stamp_us = 20u;
    CHECK(covey_traffic_put_track(&t, 2u, &b, 1.5f, 2.0f) == COVEY_OK);
    CHECK(covey_traffic_put_track(&t, 3u, &b, NAN, 0.0f) == COVEY_ERR_NONFINITE && t.n == 2);
    CHECK(covey_traffic_put_track(&t, 3u, &b, 0.0f, 2.0e3f) == COVEY_ERR_RANGE && t.n == 2);
    CHECK(covey_traffic_prune(&t, 25u, 10u) == 1 && t.n == 1);
    CHECK(t.id[0] == 2u && t.vel_m_s[0][0] == 1.5f && t.vel_m_s[0][1] == 2.0f);

    /* the traffic classes travel with their reports too; put_track is a covey neighbour */
    CHECK(t.non_cooperative[0] == 0u && t.manned[0] == 0u);
    b.stamp_us = 30u;
    CHECK(covey_traffic_put_classified(&t, 0x3C6444u, &b, 30.0f, 0.0f, 1, 1) == COVEY_OK);
    b.stamp_us = 40u;
    CHECK(covey_traffic_put_classified(&t, 0x2000001u, &b, 2.0f, 0.0f, 7, 0) == COVEY_OK);
    CHECK(covey_traffic_prune(&t, 45u, 15u) == 1 && t.n == 2);
    CHECK(t.id[0] == 0x3C6444u && t.non_cooperative[0] == 1u && t.manned[0] == 1u);
    CHECK(t.id[1] == 0x2000001u && t.non_cooperative[1] == 1u && t.manned[1] == 0u);
    /* the kinds the tick takes: manned aircraft keep their own berth (COVEY_TRACK_MANNED) */
    {
        uint8_t kinds[COVEY_MAX_INPUTS] = {9u, 9u, 9u};
        CHECK(covey_traffic_put_track(&t, 5u, &b, 0.0f, 0.0f) == COVEY_OK && t.n == 3);
        CHECK(covey_traffic_kinds(&t, kinds) == 3);
        CHECK(kinds[0] == COVEY_TRACK_MANNED && kinds[1] == COVEY_TRACK_TRAFFIC &&
              kinds[2] == COVEY_TRACK_COOPERATIVE);
        CHECK(covey_traffic_kinds(NULL, kinds) == 0 && covey_traffic_kinds(&t, NULL) == 0);
        CHECK(covey_traffic_prune(&t, 45u, 15u) == 0 && t.n == 3);
        t.n = 2; /* back to the two traffic tracks */
    }
    /* covey's marking: block address, CVY callsign, UAV emitter; all three needed */
    CHECK(covey_traffic_is_covey(COVEY_TRAFFIC_ICAO_BASE | 7u, "CVY7", COVEY_ADSB_EMITTER_UAV));
    CHECK(!covey_traffic_is_covey(7u, "CVY7", COVEY_ADSB_EMITTER_UAV));
    CHECK(!covey_traffic_is_covey(COVEY_TRAFFIC_ICAO_BASE | 7u, "DLH7", COVEY_ADSB_EMITTER_UAV));
    CHECK(!covey_traffic_is_covey(COVEY_TRAFFIC_ICAO_BASE | 7u, "CVY7", 1));
    CHECK(!covey_traffic_is_covey(COVEY_TRAFFIC_ICAO_BASE | 7u, NULL, COVEY_ADSB_EMITTER_UAV));
    CHECK(covey_emitter_is_manned(1) && covey_emitter_is_manned(7) && covey_emitter_is_manned(9));
    CHECK(!covey_emitter_is_manned(0) && !covey_emitter_is_manned(8) &&
          !covey_emitter_is_manned(COVEY_ADSB_EMITTER_UAV) && !covey_emitter_is_manned(19));
}

static void test_heading(void)
{
    covey_heading_t h;
    memset(&h, 0, sizeof h);
    covey_goal_t g = {0.0f, 10.0f};
    CHECK(fabsf(covey_heading_for_goal(&h, 0.0f, 0.0f, &g) - 1.5707964f) < 1e-6f);
    covey_command_t cmd;
    memset(&cmd, 0, sizeof cmd);
    cmd.vel_n_m_s = -1.0f;
    covey_heading_after_command(&h, &cmd);
    CHECK(fabsf(h.heading_rad - 3.1415927f) < 1e-6f);
    /* same goal: the heading follows the commands, not the goal */
    CHECK(fabsf(covey_heading_for_goal(&h, 5.0f, 0.0f, &g) - 3.1415927f) < 1e-6f);
    cmd.vel_n_m_s = 0.01f; /* hover: keep */
    covey_heading_after_command(&h, &cmd);
    CHECK(fabsf(h.heading_rad - 3.1415927f) < 1e-6f);
    covey_goal_t g2 = {10.0f, 0.0f}; /* new goal, due north */
    CHECK(fabsf(covey_heading_for_goal(&h, 0.0f, 0.0f, &g2)) < 1e-6f);
    covey_goal_t here = {0.0f, 0.0005f}; /* within 1 mm: keep */
    CHECK(fabsf(covey_heading_for_goal(&h, 0.0f, 0.0f, &here)) < 1e-6f);
}

static void test_core_edges(void)
{
    static covey_scratch_t s;
    covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    covey_vehicle_t own = veh(0.0f, 0.0f, 0.0f, 0u);
    covey_goal_t goal = {10.0f, 0.0f};
    covey_command_t out;
    CHECK(covey_command(NULL, &own, &goal, NULL, 0, 0u, &s, &out) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, NULL, &goal, NULL, 0, 0u, &s, &out) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, &own, NULL, NULL, 0, 0u, &s, &out) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, &own, &goal, NULL, 1, 0u, &s, &out) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, &own, &goal, NULL, 0, 0u, NULL, &out) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, &own, &goal, NULL, 0, 0u, &s, NULL) == COVEY_ERR_NULL);
    CHECK(covey_command(&cfg, &own, &goal, NULL, 0, 0u, &s, &out) == COVEY_OK);
    CHECK(isfinite(out.vel_n_m_s) && out.n_used == 0);
    float a[2];
    float g1[COVEY_GOAL] = {0.0f};
    CHECK(covey_action(NULL, 0, g1, &s, a) == COVEY_OK);
    CHECK(covey_action(NULL, 1, g1, &s, a) == COVEY_ERR_NULL);
    CHECK(covey_config_check(NULL) == COVEY_ERR_NULL);
    CHECK(strcmp(covey_status_name(COVEY_ERR_STALE), "stale") == 0);
    CHECK(strcmp(covey_status_name((covey_status_t)42), "unknown") == 0);

    /* two neighbours at the same distance: selection with max 1 keeps the lower index */
    covey_vehicle_t nb[3] = {veh(0.0f, 5.0f, 1.0f, 0u), veh(0.0f, -5.0f, 2.0f, 0u),
                             veh(50.0f, 0.0f, 0.0f, 0u)};
    covey_config_t one = cfg;
    one.max_neighbours = 1;
    covey_command_t o1, o2;
    CHECK(covey_command(&one, &own, &goal, nb, 3, 0u, &s, &o1) == COVEY_OK);
    CHECK(covey_command(&one, &own, &goal, nb, 1, 0u, &s, &o2) == COVEY_OK);
    CHECK(o1.n_used == 1 && o1.n_excess + o1.n_far == 2);
    CHECK(o1.action[0] == o2.action[0] && o1.action[1] == o2.action[1]);

    /* a neighbour exactly behind (bearing -pi): finite output, no fault */
    covey_vehicle_t behind = veh(-5.0f, 0.0f, 0.0f, 0u);
    CHECK(covey_command(&cfg, &own, &goal, &behind, 1, 0u, &s, &out) == COVEY_OK);
    CHECK(isfinite(out.action[0]) && isfinite(out.action[1]));
    /* on top of the vehicle (d = 0, atan2(0, 0) = 0): finite */
    covey_vehicle_t same = veh(0.0f, 0.0f, 0.0f, 0u);
    CHECK(covey_command(&cfg, &own, &goal, &same, 1, 0u, &s, &out) == COVEY_OK);
    CHECK(isfinite(out.action[0]) && isfinite(out.action[1]));
}

static void test_loop(void)
{
    /* traffic table + heading + core, as the PX4 module runs them */
    static covey_traffic_t t;
    static covey_scratch_t s;
    covey_traffic_init(&t);
    covey_config_t cfg = {3.0f, 2.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    covey_heading_t hs;
    memset(&hs, 0, sizeof hs);
    covey_goal_t goal = {30.0f, 0.0f};
    float pn = 0.0f, pe = 0.0f;
    for (uint32_t step = 0; step < 50; ++step) {
        uint64_t now = 1000000u + 100000u * step;
        covey_vehicle_t intruder = veh(15.0f - 0.2f * (float)step, 0.5f, 3.14159f, now);
        CHECK(covey_traffic_put(&t, 42u, &intruder) == COVEY_OK);
        covey_traffic_prune(&t, now, cfg.max_neighbour_age_us);
        covey_vehicle_t own = veh(pn, pe, covey_heading_for_goal(&hs, pn, pe, &goal), now);
        covey_command_t out;
        CHECK(covey_command(&cfg, &own, &goal, t.report, t.n, now, &s, &out) == COVEY_OK);
        CHECK(out.n_used == 1);
        CHECK(hypotf(out.vel_n_m_s, out.vel_e_m_s) <= cfg.cruise_speed_m_s * 1.000001f);
        covey_heading_after_command(&hs, &out);
        pn += 0.1f * out.vel_n_m_s;
        pe += 0.1f * out.vel_e_m_s;
    }
}

static void test_safety_edges(void)
{
    static covey_safety_scratch_t ss;
    covey_safety_config_t sc = covey_safety_defaults(3.0f, 1.0f);
    CHECK(covey_safety_config_check(&sc) == COVEY_OK);
    CHECK(covey_safety_config_check(NULL) == COVEY_ERR_NULL);
    covey_safety_config_t bad = sc;
    bad.responsibility = 0.0f;
    CHECK(covey_safety_config_check(&bad) == COVEY_ERR_RANGE);
    bad = sc;
    bad.dt_s = NAN;
    CHECK(covey_safety_config_check(&bad) == COVEY_ERR_NONFINITE);
    covey_track_t me = {0.0f, 0.0f, 1.0f, 0.0f, 0u, 0.0f, 0u};
    covey_track_t other = {6.0f, 0.0f, -1.0f, 0.0f, 0u, 0.0f, 0u};
    float pref[2] = {1.0f, 0.0f};
    covey_safety_out_t o;
    CHECK(covey_safety_filter(&sc, &me, pref, NULL, 1, &ss, &o) == COVEY_ERR_NULL);
    CHECK(covey_safety_filter(&sc, &me, NULL, &other, 1, &ss, &o) == COVEY_ERR_NULL);
    CHECK(covey_safety_filter(&sc, &me, pref, &other, -1, &ss, &o) == COVEY_ERR_RANGE);
    CHECK(covey_safety_filter(&sc, &me, pref, NULL, 0, &ss, &o) == COVEY_OK && !o.changed);
    /* head-on at 6 m, closing at 2 m/s: it must steer off the line and keep |v| <= 1 */
    CHECK(covey_safety_filter(&sc, &me, pref, &other, 1, &ss, &o) == COVEY_OK);
    CHECK(o.changed && o.n_lines == 1 && fabsf(o.vel_e_m_s) > 0.1f);
    CHECK(o.vel_n_m_s * o.vel_n_m_s + o.vel_e_m_s * o.vel_e_m_s <= 1.0f + 1e-6f);
    /* the same point twice (coincident vehicles): finite, inside the disc */
    covey_track_t twins[2] = {me, me};
    CHECK(covey_safety_filter(&sc, &me, pref, twins, 2, &ss, &o) == COVEY_OK);
    CHECK(isfinite(o.vel_n_m_s) && isfinite(o.vel_e_m_s));
    CHECK(o.vel_n_m_s * o.vel_n_m_s + o.vel_e_m_s * o.vel_e_m_s <= 1.0f + 1e-6f);

    /* decision hold: due when nothing is held, after 95 % of the period, on a new goal */
    covey_hold_t h;
    covey_hold_reset(&h);
    covey_goal_t g = {10.0f, 0.0f};
    CHECK(covey_hold_due(&h, &g, 0u, 1.0f) == 1);
    h.valid = 1;
    h.goal = g;
    h.decided_us = 1000000u;
    CHECK(covey_hold_due(&h, &g, 1940000u, 1.0f) == 0);
    CHECK(covey_hold_due(&h, &g, 1950000u, 1.0f) == 1);
    CHECK(covey_hold_due(&h, &g, 999999u, 1.0f) == 1); /* clock went back */
    covey_goal_t g2 = {10.0f, 1.0f};
    CHECK(covey_hold_due(&h, &g2, 1000001u, 1.0f) == 1);
    CHECK(covey_hold_due(&h, &g, 1000001u, 0.0f) == 1); /* period 0: every tick */

    static covey_guidance_scratch_t gs;
    covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    covey_guidance_config_t gc = covey_guidance_defaults(&cfg);
    CHECK(fabsf(gc.decision_period_s - 1.0f) < 1e-6f && gc.safety_filter == 1);
    covey_vehicle_t own = veh(0.0f, 0.0f, 0.0f, 0u);
    covey_vehicle_t nb = veh(6.0f, 0.0f, 3.1415927f, 0u);
    float own_v[2] = {1.0f, 0.0f};
    float nb_v[2] = {-1.0f, 0.0f};
    covey_guidance_out_t go;
    covey_hold_reset(&h);
    CHECK(covey_guidance_step(&gc, &h, &own, own_v, &g, &nb, NULL, 1, 0u, &gs, &go) == COVEY_ERR_NULL);
    CHECK(covey_guidance_step(&gc, &h, &own, own_v, &g, &nb, nb_v, 1, 0u, &gs, &go) == COVEY_OK);
    CHECK(go.decided == 1 && h.valid == 1 && go.filter.n_lines == 1);
    CHECK(covey_guidance_step(&gc, &h, &own, own_v, &g, &nb, nb_v, 1, 100000u, &gs, &go) == COVEY_OK);
    CHECK(go.decided == 0);
    covey_guidance_config_t gbad = gc;
    gbad.decision_period_s = 11.0f;
    CHECK(covey_guidance_step(&gbad, &h, &own, own_v, &g, &nb, nb_v, 1, 0u, &gs, &go) == COVEY_ERR_RANGE);
    CHECK(h.valid == 0 && go.vel_n_m_s == 0.0f && go.vel_e_m_s == 0.0f);

    /* the sparse rule: on by default; head-on at 6 m is dead-on (the policy's velocity is
       held), a crossing 2 m behind flies straight; bad input is refused by name */
    CHECK(gc.sparse_rule == 1);
    covey_hold_reset(&h);
    CHECK(covey_guidance_step(&gc, &h, &own, own_v, &g, &nb, nb_v, 1, 0u, &gs, &go) == COVEY_OK);
    CHECK(go.decided == 1 && go.straight == 0);
    covey_sparse_out_t so;
    const covey_track_t me_s = {0.0f, 0.0f, 1.0f, 0.0f, 0u, 0.0f, 0u};
    const covey_track_t cross = {12.0f, -10.0f, 0.0f, 1.0f, 0u, 0.0f, 0u};
    const covey_goal_t far = {40.0f, 0.0f};
    const float asked[2] = {0.6f, 0.6f};
    CHECK(covey_sparse_choose(&gc.safety, &me_s, &far, asked, &cross, 1, &gs.safety, &so) == COVEY_OK);
    CHECK(so.straight == 1 && so.n_encounters == 1 && fabsf(so.vel_n_m_s - 1.0f) < 1e-6f);
    CHECK(covey_sparse_choose(&gc.safety, &me_s, &far, asked, NULL, 1, &gs.safety, &so) == COVEY_ERR_NULL);
    CHECK(covey_sparse_choose(&gc.safety, &me_s, &far, asked, &cross, -1, &gs.safety, &so) == COVEY_ERR_RANGE);
    const float nan_v[2] = {NAN, 0.0f};
    CHECK(covey_sparse_choose(&gc.safety, &me_s, &far, nan_v, &cross, 1, &gs.safety, &so) == COVEY_ERR_NONFINITE);
    CHECK(so.straight == 0 && so.vel_n_m_s == 0.0f);
}

int main(void)
{
    test_traffic();
    test_heading();
    test_core_edges();
    test_safety_edges();
    test_loop();
    if (failures) {
        fprintf(stderr, "covey_unit: %d of %d checks failed\n", failures, checks);
        return 1;
    }
    printf("covey_unit: %d checks passed\n", checks);
    return 0;
}
