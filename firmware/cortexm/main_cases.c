/*
 * main_cases.c - Cortex-M7 image that evaluates the shared test cases and
 * measures the cost of one evaluation, printing over semihosting:
 *   R <case> <status> <vel_n> <vel_e> <a_fwd> <a_right> <n_used>  (floats as hex bits)
 *   CAL <loop iterations> <systick ticks>     (a 2-instruction loop, for calibration)
 *   B <neighbours> <systick ticks>            (one covey_command, min of BENCH_REPS)
 *   F <neighbours> <systick ticks> <lines> <infeasible>  (one covey_safety_filter, same
 *                                              neighbours, all closing in)
 *   S <neighbours> <systick ticks> <straight>  (one covey_sparse_choose on that scene,
 *                                              the goal behind us)
 * The cases come from a generated header (firmware/cortexm.py writes it).
 */
#include <math.h>
#include <string.h>

#include "covey_guidance.h"
#include "covey_policy.h"
#include "covey_safety.h"
#include "cortexm_cases.h"
#include "semihost.h"

#define BENCH_REPS 3
#define CAL_ITERATIONS 200000u

static covey_scratch_t scratch;
static covey_safety_scratch_t safety_scratch;
static covey_track_t tracks[COVEY_MAX_INPUTS];

static uint32_t bits(float x)
{
    uint32_t u;
    memcpy(&u, &x, sizeof u);
    return u;
}

static void put_field_hex(float x)
{
    sh_puts(" ");
    sh_put_hex32(bits(x));
}

/* "subs; bne" = 2 instructions per iteration: the SysTick ticks it takes tell
 * how many instructions one tick stands for under qemu -icount. */
static uint32_t calibrate(uint32_t iterations)
{
    uint32_t t0 = systick_now();
    __asm volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(iterations) : : "cc");
    return systick_elapsed(t0, systick_now());
}

int main(void)
{
    covey_command_t out;
    for (int32_t i = 0; i < CM_N_CASES; ++i) {
        covey_status_t st = covey_command(&cm_cfg[i], &cm_own[i], &cm_goal[i],
                                          &cm_nbrs[cm_first[i]], cm_count[i], cm_now[i],
                                          &scratch, &out);
        sh_puts("R ");
        sh_put_dec(i);
        sh_puts(" ");
        sh_put_dec((int32_t)st);
        put_field_hex(out.vel_n_m_s);
        put_field_hex(out.vel_e_m_s);
        put_field_hex(out.action[0]);
        put_field_hex(out.action[1]);
        sh_puts(" ");
        sh_put_dec(out.n_used);
        sh_puts("\n");
    }

    systick_start();
    sh_puts("CAL ");
    sh_put_dec((int32_t)CAL_ITERATIONS);
    sh_puts(" ");
    sh_put_dec((int32_t)calibrate(CAL_ITERATIONS));
    sh_puts("\n");
    for (int32_t b = 0; b < CM_N_BENCH; ++b) {
        uint32_t best = 0xFFFFFFFFu;
        for (int rep = 0; rep < BENCH_REPS; ++rep) {
            uint32_t t0 = systick_now();
            covey_status_t st = covey_command(&cm_bench_cfg, &cm_bench_own, &cm_bench_goal,
                                              cm_bench_nbrs, cm_bench_k[b], cm_bench_now,
                                              &scratch, &out);
            uint32_t dt = systick_elapsed(t0, systick_now());
            if (st != COVEY_OK || out.n_used != cm_bench_k[b]) {
                sh_puts("BENCHFAIL\n");
                return 2;
            }
            best = (dt < best) ? dt : best;
        }
        sh_puts("B ");
        sh_put_dec(cm_bench_k[b]);
        sh_puts(" ");
        sh_put_dec((int32_t)best);
        sh_puts("\n");
    }
    /* the filter on the same scene: every neighbour flies at us at 1 m/s, we fly north */
    const covey_safety_config_t scfg = covey_safety_defaults(cm_bench_cfg.separation_m,
                                                             cm_bench_cfg.cruise_speed_m_s);
    const covey_track_t me = {cm_bench_own.pos_n_m, cm_bench_own.pos_e_m, 1.0f, 0.0f, 0u, 0.0f, 0u};
    const float pref[2] = {1.0f, 0.0f};
    for (int32_t b = 0; b < CM_N_BENCH; ++b) {
        const int32_t k = cm_bench_k[b];
        for (int32_t i = 0; i < k; ++i) {
            const float dn = me.pos_n_m - cm_bench_nbrs[i].pos_n_m;
            const float de = me.pos_e_m - cm_bench_nbrs[i].pos_e_m;
            const float d = sqrtf(dn * dn + de * de) + 1e-6f;
            tracks[i].pos_n_m = cm_bench_nbrs[i].pos_n_m;
            tracks[i].pos_e_m = cm_bench_nbrs[i].pos_e_m;
            tracks[i].vel_n_m_s = dn / d;
            tracks[i].vel_e_m_s = de / d;
        }
        uint32_t best = 0xFFFFFFFFu;
        covey_safety_out_t fout;
        for (int rep = 0; rep < BENCH_REPS; ++rep) {
            uint32_t t0 = systick_now();
            covey_status_t st = covey_safety_filter(&scfg, &me, pref, tracks, k, &safety_scratch,
                                                    &fout);
            uint32_t dt = systick_elapsed(t0, systick_now());
            if (st != COVEY_OK) {
                sh_puts("BENCHFAIL\n");
                return 2;
            }
            best = (dt < best) ? dt : best;
        }
        sh_puts("F ");
        sh_put_dec(k);
        sh_puts(" ");
        sh_put_dec((int32_t)best);
        sh_puts(" ");
        sh_put_dec(fout.n_lines);
        sh_puts(" ");
        sh_put_dec(fout.infeasible);
        sh_puts("\n");
        /* the sparse rule on the same scene: its encounter scan, and its own filter call
           when at most two neighbours are encounters (bench/firmware_cortexm.py counts a
           full filter call on top, as the upper bound) */
        const covey_goal_t away = {me.pos_n_m - 50.0f, me.pos_e_m};
        covey_sparse_out_t sout;
        best = 0xFFFFFFFFu;
        for (int rep = 0; rep < BENCH_REPS; ++rep) {
            uint32_t t0 = systick_now();
            covey_status_t st = covey_sparse_choose(&scfg, &me, &away, pref, tracks, k,
                                                    &safety_scratch, &sout);
            uint32_t dt = systick_elapsed(t0, systick_now());
            if (st != COVEY_OK) {
                sh_puts("BENCHFAIL\n");
                return 2;
            }
            best = (dt < best) ? dt : best;
        }
        sh_puts("S ");
        sh_put_dec(k);
        sh_puts(" ");
        sh_put_dec((int32_t)best);
        sh_puts(" ");
        sh_put_dec(sout.straight);
        sh_puts("\n");
    }
    sh_puts("DONE\n");
    return 0;
}
