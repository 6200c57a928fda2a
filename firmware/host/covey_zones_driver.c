/*
 * covey_zones_driver.c - line-oriented host driver of the keep-out zones (covey_zones.c), for
 * the sanitizer fuzz test (tests/test_zones_filter.py; firmware/hostbuild.py builds it).
 *
 * stdin, one case per line, whitespace-separated tokens:
 *   n_polygons has_fence radius_m horizon_s n_counts [count] * n_counts
 *     n_values [value] * n_values            (the vertices, north east pairs back to back)
 *     own_n own_e own_vn own_ve own_sigma_m pref_n pref_e
 * n_polygons is passed to covey_zones_init as given (it may disagree with n_counts or be out of
 * range: the core must say RANGE before reading past what is there); the arrays are
 * zero-filled to their full size, so a core that reads beyond n_counts / n_values reads zeros
 * (and ASan catches reads beyond the arrays).
 * stdout, one line per case: init_status filter_status vel_n vel_e n_lines
 * (filter_status and the rest are "-" when init failed). Floats are %.9g; "nan", "inf" parse.
 */
#include "covey_zones.h"

#include <stdio.h>
#include <stdlib.h>

#define MAX_COUNTS (COVEY_MAX_ZONE_POLYGONS + 4)
#define MAX_VALUES (2 * COVEY_MAX_ZONE_VERTICES + 8)

static int read_f(float *x)
{
    char buf[64];
    if (scanf("%63s", buf) != 1) {
        return 0;
    }
    *x = strtof(buf, NULL);
    return 1;
}

static int read_i(long *x)
{
    return scanf("%ld", x) == 1;
}

int main(void)
{
    static covey_zones_t zones;
    static covey_safety_scratch_t scratch;
    static float values[MAX_VALUES];
    static int32_t counts[MAX_COUNTS];
    long n_polygons, has_fence, n_counts, n_values;
    float radius, horizon;
    while (read_i(&n_polygons)) {
        if (!read_i(&has_fence) || !read_f(&radius) || !read_f(&horizon) || !read_i(&n_counts) ||
            n_counts < 0 || n_counts > MAX_COUNTS) {
            return 2;
        }
        for (long i = 0; i < MAX_COUNTS; ++i) {
            counts[i] = 0;
        }
        for (long i = 0; i < n_counts; ++i) {
            long c;
            if (!read_i(&c)) {
                return 2;
            }
            counts[i] = (int32_t)c;
        }
        if (!read_i(&n_values) || n_values < 0 || n_values > MAX_VALUES) {
            return 2;
        }
        for (long i = 0; i < MAX_VALUES; ++i) {
            values[i] = 0.0f;
        }
        for (long i = 0; i < n_values; ++i) {
            if (!read_f(&values[i])) {
                return 2;
            }
        }
        covey_track_t own = {0};
        float pref[2];
        if (!read_f(&own.pos_n_m) || !read_f(&own.pos_e_m) || !read_f(&own.vel_n_m_s) ||
            !read_f(&own.vel_e_m_s) || !read_f(&own.pos_sigma_m) || !read_f(&pref[0]) ||
            !read_f(&pref[1])) {
            return 2;
        }
        const covey_status_t st = covey_zones_init(&zones, values, counts, (int32_t)n_polygons,
                                                   (int32_t)has_fence, radius, horizon);
        if (st != COVEY_OK) {
            printf("%d - - - -\n", (int)st);
            continue;
        }
        const covey_safety_config_t cfg = covey_safety_defaults(3.0f, 1.0f);
        covey_safety_out_t out;
        const covey_status_t fs =
            covey_safety_filter_zones(&cfg, &zones, &own, pref, NULL, 0, &scratch, &out);
        printf("%d %d %.9g %.9g %d\n", (int)st, (int)fs, (double)out.vel_n_m_s,
               (double)out.vel_e_m_s, (int)out.n_lines);
    }
    return 0;
}
