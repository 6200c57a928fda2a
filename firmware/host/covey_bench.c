/*
 * covey_bench.c - host time of one covey_command against the neighbour count.
 * For each count k: REPEATS timed batches of BATCH calls on one scene whose
 * first k neighbours are all used; prints "k median_ns_per_call min_ns_per_call".
 * The scene is fixed here (a ring of neighbours within 8 m) so no input is needed.
 */
#define _POSIX_C_SOURCE 199309L
#include "covey_policy.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define REPEATS 15
#define BATCH 20

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec * 1e9 + (double)ts.tv_nsec;
}

int main(int argc, char **argv)
{
    static covey_scratch_t scratch;
    static covey_vehicle_t nbrs[COVEY_MAX_NEIGHBOURS];
    const covey_config_t cfg = {3.0f, 1.0f, 1000000u, 500000u, COVEY_MAX_NEIGHBOURS};
    const covey_vehicle_t own = {0.0f, 0.0f, 0.3f, 1000u};
    const covey_goal_t goal = {40.0f, 25.0f};
    for (int i = 0; i < COVEY_MAX_NEIGHBOURS; ++i) {
        /* golden-angle spiral: distinct distances 1.5..8 m, varied bearings and headings */
        float r = 1.5f + 6.5f * (float)i / (float)COVEY_MAX_NEIGHBOURS;
        float a = 2.39996323f * (float)i;
        covey_vehicle_t v = {r * cosf(a), r * sinf(a), 0.7f * (float)i - 3.0f, 1000u};
        v.heading_rad = fmodf(v.heading_rad, 3.14159265f);
        nbrs[i] = v;
    }
    for (int arg = 1; arg < argc; ++arg) {
        int k = atoi(argv[arg]);
        if (k < 0 || k > COVEY_MAX_NEIGHBOURS) {
            fprintf(stderr, "neighbour count %d outside [0, %d]\n", k, COVEY_MAX_NEIGHBOURS);
            return 2;
        }
        double per_call_ns[REPEATS];
        covey_command_t out;
        for (int rep = 0; rep < REPEATS; ++rep) {
            double t0 = now_ns();
            for (int b = 0; b < BATCH; ++b) {
                if (covey_command(&cfg, &own, &goal, nbrs, k, 1000u, &scratch, &out) != COVEY_OK ||
                    out.n_used != k) {
                    fprintf(stderr, "bench scene rejected at k=%d\n", k);
                    return 3;
                }
            }
            per_call_ns[rep] = (now_ns() - t0) / BATCH;
        }
        qsort(per_call_ns, REPEATS, sizeof(double), cmp_double);
        printf("%d %.1f %.1f\n", k, per_call_ns[REPEATS / 2], per_call_ns[0]);
    }
    return 0;
}
