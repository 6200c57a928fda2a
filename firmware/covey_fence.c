/*
 * covey_fence.c - zones from an autopilot's geofence items; see covey_fence.h.
 */
#include "covey_fence.h"

#include <math.h>
#include <stddef.h>

#define FENCE_PI 3.14159265358979323846

float covey_zone_radius_m(const covey_safety_config_t *cfg)
{
    if (cfg == NULL) {
        return 0.0f;
    }
    return COVEY_ZONE_CLEARANCE_SHARE * cfg->radius_m * (1.0f + cfg->margin);
}

/* Appends one polygon of n vertices; the inclusion shape is kept apart (it goes last). */
typedef struct {
    int32_t n_polygons;
    int32_t n_vertices;
} fence_count_t;

static int32_t room(const fence_count_t *c, int32_t n)
{
    return c->n_polygons < COVEY_MAX_ZONE_POLYGONS && n <= COVEY_MAX_ZONE_VERTICES - c->n_vertices;
}

covey_status_t covey_fence_zones(covey_zones_t *zones, const covey_fence_item_t *items,
                                 int32_t n_items, const covey_safety_config_t *cfg,
                                 covey_fence_scratch_t *scratch)
{
    if (zones == NULL || cfg == NULL || scratch == NULL || (items == NULL && n_items > 0)) {
        return COVEY_ERR_NULL;
    }
    zones->n_vertices = 0;
    if (n_items < 0 || n_items > COVEY_FENCE_MAX_ITEMS) {
        return COVEY_ERR_RANGE;
    }
    covey_status_t st = covey_safety_config_check(cfg);
    if (st != COVEY_OK) {
        return st;
    }
    /* two passes: keep-out shapes first, then the one inclusion shape (covey_zones_init wants
     * the fence last) */
    fence_count_t c = {0, 0};
    int32_t inclusions = 0;
    for (int32_t pass = 0; pass < 2; ++pass) {
        int32_t i = 0;
        while (i < n_items) {
            const covey_fence_item_t *it = &items[i];
            const int32_t cmd = it->command;
            const int32_t polygon =
                cmd == COVEY_FENCE_POLYGON_INCLUSION || cmd == COVEY_FENCE_POLYGON_EXCLUSION;
            const int32_t circle =
                cmd == COVEY_FENCE_CIRCLE_INCLUSION || cmd == COVEY_FENCE_CIRCLE_EXCLUSION;
            const int32_t inclusion =
                cmd == COVEY_FENCE_POLYGON_INCLUSION || cmd == COVEY_FENCE_CIRCLE_INCLUSION;
            if (!polygon && !circle) {
                ++i; /* a return point or another item: not a zone */
                continue;
            }
            int32_t n = 1;
            if (polygon) {
                n = it->vertex_count;
                if (n < 3 || n > n_items - i) {
                    return COVEY_ERR_RANGE;
                }
                for (int32_t k = 1; k < n; ++k) {
                    if (items[i + k].command != cmd || items[i + k].vertex_count != n) {
                        return COVEY_ERR_RANGE;
                    }
                }
            } else {
                if (!isfinite(it->pos_n_m) || !isfinite(it->pos_e_m) || !isfinite(it->radius_m)) {
                    return COVEY_ERR_NONFINITE;
                }
                if (!(it->radius_m > 0.0f && it->radius_m <= COVEY_MAX_ABS_POS_M)) {
                    return COVEY_ERR_RANGE;
                }
            }
            if (pass == 0 && inclusion && ++inclusions > 1) {
                return COVEY_ERR_RANGE;
            }
            if (inclusion == pass) { /* pass 0: keep-out shapes; pass 1: the fence */
                const int32_t nv = polygon ? n : COVEY_FENCE_CIRCLE_VERTICES;
                if (!room(&c, nv)) {
                    return COVEY_ERR_RANGE;
                }
                float *v = &scratch->vertices_ne_m[2 * c.n_vertices];
                if (polygon) {
                    for (int32_t k = 0; k < n; ++k) {
                        v[2 * k] = items[i + k].pos_n_m;
                        v[2 * k + 1] = items[i + k].pos_e_m;
                    }
                } else {
                    /* inscribed (vertices on the circle) for inclusion, circumscribed (vertices
                     * at r / cos(pi / k)) for exclusion; in double, as comms/plan_io.py */
                    const double r = inclusion
                                         ? (double)it->radius_m
                                         : (double)it->radius_m /
                                               cos(FENCE_PI / COVEY_FENCE_CIRCLE_VERTICES);
                    for (int32_t k = 0; k < nv; ++k) {
                        const double a = 2.0 * FENCE_PI * k / COVEY_FENCE_CIRCLE_VERTICES;
                        v[2 * k] = (float)((double)it->pos_n_m + r * cos(a));
                        v[2 * k + 1] = (float)((double)it->pos_e_m + r * sin(a));
                    }
                }
                scratch->counts[c.n_polygons++] = nv;
                c.n_vertices += nv;
            }
            i += n;
        }
    }
    if (c.n_polygons == 0) {
        return COVEY_OK;
    }
    st = covey_zones_init(zones, scratch->vertices_ne_m, scratch->counts, c.n_polygons,
                          inclusions, covey_zone_radius_m(cfg), COVEY_ZONE_TIME_HORIZON_S);
    if (st != COVEY_OK) {
        zones->n_vertices = 0;
    }
    return st;
}
