/*
 * covey_fence_driver.c - line-oriented host driver of covey_fence_zones (covey_fence.c), for the
 * sanitizer fuzz test (tests/test_px4_sky.py; firmware/hostbuild.py builds it).
 *
 * stdin, one case per line, whitespace-separated tokens:
 *   n_items n_given [command vertex_count north east radius] * n_given
 * n_items is passed to covey_fence_zones as given (it may disagree with n_given or be out of
 * range: the core must say RANGE before reading past what is there); the item array is
 * zero-filled to its full size. stdout, one line per case: status n_vertices n_lines, n_lines
 * the zone lines of a vehicle at the origin (covey_zones_lines, 1 m/s, no padding).
 */
#include "covey_fence.h"

#include <stdio.h>
#include <stdlib.h>

#define MAX_ITEMS 1200

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
    static covey_fence_scratch_t scratch;
    static covey_fence_item_t items[MAX_ITEMS];
    static covey_halfplane_t lines[COVEY_MAX_ZONE_EDGES];
    const covey_safety_config_t cfg = covey_safety_defaults(3.0f, 1.0f);
    long n_items, n_given;
    while (read_i(&n_items)) {
        if (!read_i(&n_given) || n_given < 0 || n_given > MAX_ITEMS) {
            return 2;
        }
        for (long i = 0; i < MAX_ITEMS; ++i) {
            items[i] = (covey_fence_item_t){0, 0, 0.0f, 0.0f, 0.0f};
        }
        for (long i = 0; i < n_given; ++i) {
            long cmd, count;
            if (!read_i(&cmd) || !read_i(&count) || !read_f(&items[i].pos_n_m) ||
                !read_f(&items[i].pos_e_m) || !read_f(&items[i].radius_m)) {
                return 2;
            }
            items[i].command = (int32_t)cmd;
            items[i].vertex_count = (int32_t)count;
        }
        /* never more than the array holds: a larger n_items must be refused before any read */
        const int32_t n = n_items > MAX_ITEMS && n_items <= COVEY_FENCE_MAX_ITEMS
                              ? MAX_ITEMS
                              : (int32_t)n_items;
        const covey_status_t st = covey_fence_zones(&zones, items, n, &cfg, &scratch);
        const covey_track_t own = {0.0f, 0.0f, 1.0f, 0.0f, 0u, 0.0f, 0u};
        const int32_t n_lines = covey_zones_lines(&zones, &own, 1.0f, 0.0f, lines);
        printf("%s %d %d\n", covey_status_name(st), (int)zones.n_vertices, (int)n_lines);
    }
    return 0;
}
