/*
 * covey_zones.h - keep-out zones as static constraints of the separation filter, in C99: ORCA's
 * obstacle half-planes (van den Berg et al. 2011, section 5.3; RVO2's obstacle lines), the twin
 * of policy/zone_lines.py (parity tested, tests/test_zones_filter.py).
 *
 * For each zone edge near the vehicle, the velocities that would bring it within radius_m of
 * the edge within time_horizon_s form a truncated cone; its half-plane is passed to the filter's
 * LP before the neighbours' lines and is never relaxed (covey_safety_filter_hard), so traffic
 * can never push a vehicle into a zone. v = 0 meets every zone line of a vehicle outside the
 * radius, so the zone lines alone are always feasible.
 *
 * Keep-out polygons are stored counter-clockwise in (north, east), an inclusion fence clockwise:
 * an edge constrains a vehicle on its right, the side it faces. Concave polygons are fine.
 *
 * Same rules as covey_policy.h: caller-owned storage, no malloc, float32 inputs (the geometry in
 * covey_real_t, double by default), inputs checked with isfinite then range, faults as
 * covey_status_t.
 */
#ifndef COVEY_ZONES_H
#define COVEY_ZONES_H

#include "covey_safety.h"

#ifdef __cplusplus
extern "C" {
#endif

#define COVEY_MAX_ZONE_VERTICES 512 /* all polygons together */
#define COVEY_MAX_ZONE_POLYGONS 64
/* Nearest facing edges that get a line per call (policy/zone_lines.py MAX_ZONE_EDGES); the
 * filter's hard lines, COVEY_SAFETY_MAX_HARD_LINES. */
#define COVEY_MAX_ZONE_EDGES COVEY_SAFETY_MAX_HARD_LINES

/* Prepared zones (covey_zones_init): every polygon's vertices in one array. */
typedef struct {
    covey_real_t point[COVEY_MAX_ZONE_VERTICES][2];    /* north, east, metres */
    covey_real_t unit_dir[COVEY_MAX_ZONE_VERTICES][2]; /* unit vector to the next vertex */
    int32_t next[COVEY_MAX_ZONE_VERTICES];
    int32_t prev[COVEY_MAX_ZONE_VERTICES];
    int32_t convex[COVEY_MAX_ZONE_VERTICES]; /* 1: convex on the side the edges face */
    int32_t n_vertices;
    float radius_m;       /* (0, 1000]: distance kept from every edge */
    float time_horizon_s; /* [1e-3, 1000]: how far ahead edges are looked at (tau_obst) */
} covey_zones_t;

/*
 * Prepares zones from n_polygons polygons: counts[k] vertices each, (north, east) pairs in
 * vertices_ne_m back to back (2 floats a vertex), the last `has_fence` (0 or 1) of them the
 * inclusion fence. Checks, first failure returned: NULL, counts (3 or more each, the total at
 * most COVEY_MAX_ZONE_VERTICES, n_polygons at most COVEY_MAX_ZONE_POLYGONS), then the vertices
 * (non-finite before beyond COVEY_MAX_ABS_POS_M), then the geometry (a repeated neighbour
 * vertex, no area, or edges that cross: COVEY_ERR_RANGE), then radius_m and time_horizon_s.
 * policy/zone_lines.py ZoneSet.of does the same (it drops repeated vertices instead).
 */
covey_status_t covey_zones_init(covey_zones_t *zones, const float *vertices_ne_m,
                                const int32_t *counts, int32_t n_polygons, int32_t has_fence,
                                float radius_m, float time_horizon_s);

/*
 * The obstacle half-planes of `own` (position; its velocity picks each cone's side), at most
 * COVEY_MAX_ZONE_EDGES edges (nearest first, ties by index) within time_horizon_s
 * max_speed_m_s + radius_m + pad_m that face it, keeping radius_m + pad_m (pad_m: sigma_k x
 * the own position 1-sigma; negative is 0). A vehicle found within that distance of an edge
 * must move away at (distance short) / 1 s, at most half of max_speed_m_s. Returns the number
 * of lines written, or -1 on NULL. Inputs are not checked here (covey_safety_filter_zones
 * does).
 */
int32_t covey_zones_lines(const covey_zones_t *zones, const covey_track_t *own,
                          float max_speed_m_s, float pad_m, covey_halfplane_t *lines);

/*
 * covey_safety_filter with the zones' lines as hard constraints (zones NULL: exactly
 * covey_safety_filter), padded by cfg->sigma_k x own->pos_sigma_m. out->n_lines counts the
 * neighbours' and the zones' lines.
 */
covey_status_t covey_safety_filter_zones(const covey_safety_config_t *cfg,
                                         const covey_zones_t *zones, const covey_track_t *own,
                                         const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                         int32_t n_nbrs, covey_safety_scratch_t *scratch,
                                         covey_safety_out_t *out);

/* sizeof(covey_zones_t), for bindings (ctypes). */
uint32_t covey_zones_bytes(void);

#ifdef __cplusplus
}
#endif

#endif /* COVEY_ZONES_H */
