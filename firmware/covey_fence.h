/*
 * covey_fence.h - keep-out zones from an autopilot's own geofence, in C99: the items PX4 keeps
 * in dataman (MAVLink mission_type FENCE; covey's agents upload the fleet plan there, docs/sky.md
 * "The autopilot's backstop") turned into the zones the separation filter keeps out of
 * (covey_zones.h), so the PX4 module flies around the same zones as the companion.
 *
 * The conversion is the one comms/plan_io.py makes of a QGC plan: polygons as they are, an
 * exclusion circle as its circumscribed COVEY_FENCE_CIRCLE_VERTICES-gon (its edges touch the
 * circle), an inclusion circle as its inscribed one: both err on the safe side. One inclusion
 * shape at most (covey's fence is one polygon).
 *
 * Same rules as covey_policy.h: caller-owned storage, no malloc, float32, faults as
 * covey_status_t.
 */
#ifndef COVEY_FENCE_H
#define COVEY_FENCE_H

#include "covey_zones.h"

#ifdef __cplusplus
extern "C" {
#endif

/* MAV_CMD values of MAVLink fence items (PX4 mission_fence_point_s.nav_cmd); any other item
 * (a return point, 5000) is skipped. */
#define COVEY_FENCE_POLYGON_INCLUSION 5001
#define COVEY_FENCE_POLYGON_EXCLUSION 5002
#define COVEY_FENCE_CIRCLE_INCLUSION 5003
#define COVEY_FENCE_CIRCLE_EXCLUSION 5004

/* comms/plan_io.py CIRCLE_VERTICES */
#define COVEY_FENCE_CIRCLE_VERTICES 32

/* The distance the filter keeps from a zone edge: this share of the padded separation,
 * radius_m (1 + margin) (policy/zone_lines.py ZONE_CLEARANCE_SHARE; 1.8 m at 3 m), and how far
 * ahead the edges are looked at (ZONE_TIME_HORIZON_S). */
#define COVEY_ZONE_CLEARANCE_SHARE 0.5f
#define COVEY_ZONE_TIME_HORIZON_S 2.0f

/* One fence item in local north/east metres (the caller projects lat/lon). */
typedef struct {
    int32_t command;      /* COVEY_FENCE_* (MAV_CMD) */
    int32_t vertex_count; /* polygon vertices: the vertex count of its polygon (param1) */
    float pos_n_m;        /* a polygon's vertex, or a circle's centre */
    float pos_e_m;
    float radius_m;       /* circles: (0, COVEY_MAX_ABS_POS_M] */
} covey_fence_item_t;

/* Caller-owned scratch of covey_fence_zones (the polygons before covey_zones_init). */
typedef struct {
    float vertices_ne_m[2 * COVEY_MAX_ZONE_VERTICES];
    int32_t counts[COVEY_MAX_ZONE_POLYGONS];
} covey_fence_scratch_t;

/* COVEY_ZONE_CLEARANCE_SHARE x radius_m (1 + margin); 0 for NULL. */
float covey_zone_radius_m(const covey_safety_config_t *cfg);

/*
 * Zones from n_items fence items, kept covey_zone_radius_m(cfg) away from, looked at
 * COVEY_ZONE_TIME_HORIZON_S ahead. A polygon is vertex_count consecutive items of one command,
 * each with that vertex_count. Checks, first failure returned: NULL, n_items in [0, 4096] and
 * cfg (covey_safety_config_check), then items in order: a polygon that is cut short, or whose
 * vertex_count is under 3 or changes within it (RANGE); a circle's centre or radius non-finite
 * (NONFINITE) or its radius out of range (RANGE); a second inclusion shape, more than
 * COVEY_MAX_ZONE_POLYGONS polygons or COVEY_MAX_ZONE_VERTICES vertices (RANGE); then
 * covey_zones_init's checks of the geometry. On any fault `zones` holds no vertices (the filter
 * then keeps none: the caller says why). No items: no zones, COVEY_OK.
 */
covey_status_t covey_fence_zones(covey_zones_t *zones, const covey_fence_item_t *items,
                                 int32_t n_items, const covey_safety_config_t *cfg,
                                 covey_fence_scratch_t *scratch);

#define COVEY_FENCE_MAX_ITEMS 4096

#ifdef __cplusplus
}
#endif

#endif /* COVEY_FENCE_H */
