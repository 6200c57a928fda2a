/*
 * covey_zones.c - keep-out zones as the filter's hard half-planes; see covey_zones.h. A
 * line-by-line port of policy/zone_lines.py (itself RVO2's obstacle lines).
 */
#include "covey_zones.h"

#include <math.h>
#include <stddef.h>

typedef covey_real_t real_t;
#if COVEY_SAFETY_DOUBLE
#define R(x) ((double)(x))
#define R_SQRT sqrt
#else
#define R(x) ((float)(x))
#define R_SQRT sqrtf
#endif
#define ZONES_EPS R(1.0e-9) /* policy/zone_lines.py EPS */
#define ZONE_RECOVER_S R(0.5)      /* policy/zone_lines.py ZONE_RECOVER_S */
#define ZONE_MAX_PUSH_SHARE R(1.0) /* ZONE_MAX_PUSH_SHARE */

/* det(a, b) = a_x b_y - a_y b_x */
static real_t det2(real_t ax, real_t ay, real_t bx, real_t by)
{
    return ax * by - ay * bx;
}

/* 1 when segments a-b and c-d share a point (collinear overlaps included) */
static int segments_meet(const real_t *a, const real_t *b, const real_t *c, const real_t *d)
{
    const real_t d1 = det2(b[0] - a[0], b[1] - a[1], c[0] - a[0], c[1] - a[1]);
    const real_t d2 = det2(b[0] - a[0], b[1] - a[1], d[0] - a[0], d[1] - a[1]);
    const real_t d3 = det2(d[0] - c[0], d[1] - c[1], a[0] - c[0], a[1] - c[1]);
    const real_t d4 = det2(d[0] - c[0], d[1] - c[1], b[0] - c[0], b[1] - c[1]);
    if (((d1 > R(0.0) && d2 < R(0.0)) || (d1 < R(0.0) && d2 > R(0.0))) &&
        ((d3 > R(0.0) && d4 < R(0.0)) || (d3 < R(0.0) && d4 > R(0.0)))) {
        return 1;
    }
    /* a touching or collinear end: within the other segment's box */
#define ON(p, q, r_, dd)                                                                     \
    ((dd) == R(0.0) && (r_)[0] >= (p[0] < q[0] ? p[0] : q[0]) &&                             \
     (r_)[0] <= (p[0] < q[0] ? q[0] : p[0]) && (r_)[1] >= (p[1] < q[1] ? p[1] : q[1]) &&     \
     (r_)[1] <= (p[1] < q[1] ? q[1] : p[1]))
    const int touch = ON(a, b, c, d1) || ON(a, b, d, d2) || ON(c, d, a, d3) || ON(c, d, b, d4);
#undef ON
    return touch;
}

covey_status_t covey_zones_init(covey_zones_t *zones, const float *vertices_ne_m,
                                const int32_t *counts, int32_t n_polygons, int32_t has_fence,
                                float radius_m, float time_horizon_s)
{
    if (zones == NULL || (n_polygons > 0 && (vertices_ne_m == NULL || counts == NULL))) {
        return COVEY_ERR_NULL;
    }
    zones->n_vertices = 0;
    if (n_polygons < 0 || n_polygons > COVEY_MAX_ZONE_POLYGONS || has_fence < 0 ||
        has_fence > 1 || has_fence > n_polygons) {
        return COVEY_ERR_RANGE;
    }
    int32_t total = 0;
    for (int32_t k = 0; k < n_polygons; ++k) {
        if (counts[k] < 3 || counts[k] > COVEY_MAX_ZONE_VERTICES - total) {
            return COVEY_ERR_RANGE;
        }
        total += counts[k];
    }
    for (int32_t i = 0; i < 2 * total; ++i) {
        if (!isfinite(vertices_ne_m[i])) {
            return COVEY_ERR_NONFINITE;
        }
    }
    for (int32_t i = 0; i < 2 * total; ++i) {
        if (fabsf(vertices_ne_m[i]) > COVEY_MAX_ABS_POS_M) {
            return COVEY_ERR_RANGE;
        }
    }
    if (!isfinite(radius_m) || !isfinite(time_horizon_s)) {
        return COVEY_ERR_NONFINITE;
    }
    if (!(radius_m > 0.0f && radius_m <= COVEY_SAFETY_MAX_RADIUS_M) ||
        !(time_horizon_s >= COVEY_SAFETY_MIN_TIME_S && time_horizon_s <= COVEY_SAFETY_MAX_TIME_S)) {
        return COVEY_ERR_RANGE;
    }
    int32_t base = 0;
    for (int32_t k = 0; k < n_polygons; ++k) {
        const int32_t n = counts[k];
        const float *v = vertices_ne_m + 2 * base;
        /* signed area x 2 in (n, e); keep-out polygons counter-clockwise, the fence clockwise */
        real_t area2 = R(0.0);
        for (int32_t i = 0; i < n; ++i) {
            const int32_t j = (i + 1) % n;
            area2 += R(v[2 * i]) * R(v[2 * j + 1]) - R(v[2 * j]) * R(v[2 * i + 1]);
        }
        const int fence = has_fence && k == n_polygons - 1;
        if (area2 == R(0.0)) {
            return COVEY_ERR_RANGE;
        }
        const int flip = (area2 > R(0.0)) == fence;
        for (int32_t i = 0; i < n; ++i) {
            const int32_t src = flip ? n - 1 - i : i;
            zones->point[base + i][0] = R(v[2 * src]);
            zones->point[base + i][1] = R(v[2 * src + 1]);
            zones->next[base + i] = base + (i + 1) % n;
            zones->prev[base + i] = base + (i + n - 1) % n;
        }
        for (int32_t i = 0; i < n; ++i) {
            const real_t *p = zones->point[base + i];
            const real_t *q = zones->point[base + (i + 1) % n];
            if (p[0] == q[0] && p[1] == q[1]) {
                return COVEY_ERR_RANGE; /* a repeated vertex: no edge direction */
            }
        }
        /* edges that cross (not neighbours): not a simple polygon */
        for (int32_t i = 0; i < n; ++i) {
            for (int32_t j = i + 2; j < n; ++j) {
                if (i == 0 && j == n - 1) {
                    continue;
                }
                if (segments_meet(zones->point[base + i], zones->point[base + (i + 1) % n],
                                  zones->point[base + j], zones->point[base + (j + 1) % n])) {
                    return COVEY_ERR_RANGE;
                }
            }
        }
        base += n;
    }
    for (int32_t i = 0; i < total; ++i) {
        const real_t *a = zones->point[zones->prev[i]];
        const real_t *b = zones->point[i];
        const real_t *c = zones->point[zones->next[i]];
        real_t dx = c[0] - b[0], dy = c[1] - b[1];
        real_t n = R_SQRT(dx * dx + dy * dy);
        n = n < ZONES_EPS ? ZONES_EPS : n;
        zones->unit_dir[i][0] = dx / n;
        zones->unit_dir[i][1] = dy / n;
        /* convex: RVO2's leftOf(prev, this, next) = det(prev - next, this - prev) >= 0 */
        zones->convex[i] = det2(a[0] - c[0], a[1] - c[1], b[0] - a[0], b[1] - a[1]) >= R(0.0);
    }
    zones->n_vertices = total;
    zones->radius_m = radius_m;
    zones->time_horizon_s = time_horizon_s;
    return COVEY_OK;
}

static void normalize(real_t x, real_t y, real_t *ox, real_t *oy)
{
    real_t n = R_SQRT(x * x + y * y);
    n = n < ZONES_EPS ? ZONES_EPS : n;
    *ox = x / n;
    *oy = y / n;
}

static void put(covey_halfplane_t *l, real_t px, real_t py, real_t dx, real_t dy)
{
    l->point[0] = px;
    l->point[1] = py;
    l->dir[0] = dx;
    l->dir[1] = dy;
}

/* The speed away from an edge found at d < r: (r - d) / ZONE_RECOVER_S, at most cap. */
static real_t push(real_t r, real_t d, real_t cap)
{
    const real_t k = (r - d) / ZONE_RECOVER_S;
    return k > cap ? cap : k;
}

int32_t covey_zones_lines(const covey_zones_t *z, const covey_track_t *own, float max_speed_m_s,
                          float pad_m, covey_halfplane_t *lines)
{
    if (z == NULL || own == NULL || lines == NULL) {
        return -1;
    }
    const real_t px = R(own->pos_n_m), py = R(own->pos_e_m);
    const real_t vx = R(own->vel_n_m_s), vy = R(own->vel_e_m_s);
    const real_t pad = pad_m >= 0.0f ? R(pad_m) : R(0.0);
    const real_t r = R(z->radius_m) + pad;
    const real_t r_sq = r * r;
    const real_t inv_tau = R(1.0) / R(z->time_horizon_s);
    const real_t reach = R(z->time_horizon_s) * R(max_speed_m_s) + R(z->radius_m) + pad;
    const real_t cap = ZONE_MAX_PUSH_SHARE * R(max_speed_m_s);

    /* the facing edges within reach, nearest first (a stable insertion sort, ties by index) */
    int32_t edge[COVEY_MAX_ZONE_EDGES];
    real_t edge_d[COVEY_MAX_ZONE_EDGES];
    int32_t n_edges = 0;
    for (int32_t i = 0; i < z->n_vertices; ++i) {
        const real_t *a = z->point[i];
        const real_t *b = z->point[z->next[i]];
        const real_t ax = a[0] - px, ay = a[1] - py;
        const real_t ex = b[0] - a[0], ey = b[1] - a[1];
        if (ax * ey - ay * ex >= R(0.0)) {
            continue; /* the vehicle is not right of a -> b: the edge faces away */
        }
        real_t s = (-ax * ex - ay * ey) / (ex * ex + ey * ey);
        s = s < R(0.0) ? R(0.0) : (s > R(1.0) ? R(1.0) : s);
        const real_t dx = ax + s * ex, dy = ay + s * ey;
        const real_t d = dx * dx + dy * dy;
        if (!(d < reach * reach)) {
            continue;
        }
        int32_t k = n_edges < COVEY_MAX_ZONE_EDGES ? n_edges : COVEY_MAX_ZONE_EDGES - 1;
        if (n_edges == COVEY_MAX_ZONE_EDGES && !(d < edge_d[k])) {
            continue; /* full, and not nearer than the farthest kept */
        }
        while (k > 0 && d < edge_d[k - 1]) {
            edge[k] = edge[k - 1];
            edge_d[k] = edge_d[k - 1];
            --k;
        }
        edge[k] = i;
        edge_d[k] = d;
        if (n_edges < COVEY_MAX_ZONE_EDGES) {
            ++n_edges;
        }
    }

    int32_t n = 0;
    for (int32_t e = 0; e < n_edges; ++e) {
        int32_t o1 = edge[e];
        int32_t o2 = z->next[o1];
        const real_t r1x = z->point[o1][0] - px, r1y = z->point[o1][1] - py;
        const real_t r2x = z->point[o2][0] - px, r2y = z->point[o2][1] - py;
        /* already covered: both cut-off points p / tau beyond an earlier line by r / tau */
        int covered = 0;
        for (int32_t j = 0; j < n && !covered; ++j) {
            const real_t qx = lines[j].point[0], qy = lines[j].point[1];
            const real_t dx = lines[j].dir[0], dy = lines[j].dir[1];
            const real_t c1 = (inv_tau * r1x - qx) * dy - (inv_tau * r1y - qy) * dx - inv_tau * r;
            const real_t c2 = (inv_tau * r2x - qx) * dy - (inv_tau * r2y - qy) * dx - inv_tau * r;
            covered = c1 >= -ZONES_EPS && c2 >= -ZONES_EPS;
        }
        if (covered) {
            continue;
        }
        const real_t dist_sq1 = r1x * r1x + r1y * r1y;
        const real_t dist_sq2 = r2x * r2x + r2y * r2y;
        const real_t ovx = z->point[o2][0] - z->point[o1][0];
        const real_t ovy = z->point[o2][1] - z->point[o1][1];
        const real_t s = (-r1x * ovx - r1y * ovy) / (ovx * ovx + ovy * ovy);
        const real_t lx_ = -r1x - s * ovx, ly_ = -r1y - s * ovy;
        const real_t dist_sq_line = lx_ * lx_ + ly_ * ly_;
        real_t dx, dy;
        /* within r at distance d: away at s = min((r - d) / recover, cap); the line passes
         * through s times the unit normal (RVO2's, through 0, only forbids approaching) */
        if (s < R(0.0) && dist_sq1 <= r_sq) {
            /* the left vertex (a reflex one: its edges do it); point -k r1 / |r1| */
            if (z->convex[o1] && dist_sq1 > R(0.0)) {
                normalize(-r1y, r1x, &dx, &dy);
                const real_t k = push(r, R_SQRT(dist_sq1), cap);
                put(&lines[n++], -k * dy, k * dx, dx, dy);
            }
            continue;
        }
        if (s > R(1.0) && dist_sq2 <= r_sq) {
            /* the right vertex; the next edge covers it unless the vehicle is beside this one */
            if (z->convex[o2] && r2x * z->unit_dir[o2][1] - r2y * z->unit_dir[o2][0] >= R(0.0) &&
                dist_sq2 > R(0.0)) {
                normalize(-r2y, r2x, &dx, &dy);
                const real_t k = push(r, R_SQRT(dist_sq2), cap);
                put(&lines[n++], -k * dy, k * dx, dx, dy);
            }
            continue;
        }
        if (s >= R(0.0) && s <= R(1.0) && dist_sq_line <= r_sq) {
            /* the edge itself: along the outward normal (e_y, -e_x) */
            const real_t ex = z->unit_dir[o1][0], ey = z->unit_dir[o1][1];
            const real_t k = push(r, R_SQRT(dist_sq_line), cap);
            put(&lines[n++], k * ey, -k * ex, -ex, -ey);
            continue;
        }
        /* no collision: the legs (tangents to the discs at the ends); seen obliquely, both
         * come from one vertex. leg = sqrt(|p|^2 - r^2):
         *   left = (p_x leg - p_y r, p_x r + p_y leg) / |p|^2,
         *   right = (p_x leg + p_y r, -p_x r + p_y leg) / |p|^2 */
        real_t left[2], right[2];
        if (s < R(0.0) && dist_sq_line <= r_sq) {
            if (!z->convex[o1]) {
                continue;
            }
            o2 = o1;
            const real_t leg1 = R_SQRT(dist_sq1 - r_sq);
            left[0] = (r1x * leg1 - r1y * r) / dist_sq1;
            left[1] = (r1x * r + r1y * leg1) / dist_sq1;
            right[0] = (r1x * leg1 + r1y * r) / dist_sq1;
            right[1] = (-r1x * r + r1y * leg1) / dist_sq1;
        } else if (s > R(1.0) && dist_sq_line <= r_sq) {
            if (!z->convex[o2]) {
                continue;
            }
            o1 = o2;
            const real_t leg2 = R_SQRT(dist_sq2 - r_sq);
            left[0] = (r2x * leg2 - r2y * r) / dist_sq2;
            left[1] = (r2x * r + r2y * leg2) / dist_sq2;
            right[0] = (r2x * leg2 + r2y * r) / dist_sq2;
            right[1] = (-r2x * r + r2y * leg2) / dist_sq2;
        } else {
            if (z->convex[o1]) {
                const real_t leg1 = R_SQRT(dist_sq1 - r_sq);
                left[0] = (r1x * leg1 - r1y * r) / dist_sq1;
                left[1] = (r1x * r + r1y * leg1) / dist_sq1;
            } else { /* a reflex left vertex: the left leg extends the cut-off line */
                left[0] = -z->unit_dir[o1][0];
                left[1] = -z->unit_dir[o1][1];
            }
            if (z->convex[o2]) {
                const real_t leg2 = R_SQRT(dist_sq2 - r_sq);
                right[0] = (r2x * leg2 + r2y * r) / dist_sq2;
                right[1] = (-r2x * r + r2y * leg2) / dist_sq2;
            } else {
                right[0] = z->unit_dir[o1][0];
                right[1] = z->unit_dir[o1][1];
            }
        }
        /* a leg never points into the neighbouring edge at a convex vertex: that edge's
         * cut-off line instead, and no line if v projects onto such a foreign leg */
        const int32_t lnb = z->prev[o1];
        int left_foreign = 0, right_foreign = 0;
        if (z->convex[o1] &&
            left[0] * -z->unit_dir[lnb][1] - left[1] * -z->unit_dir[lnb][0] >= R(0.0)) {
            left[0] = -z->unit_dir[lnb][0];
            left[1] = -z->unit_dir[lnb][1];
            left_foreign = 1;
        }
        if (z->convex[o2] && right[0] * z->unit_dir[o2][1] - right[1] * z->unit_dir[o2][0] <= R(0.0)) {
            right[0] = z->unit_dir[o2][0];
            right[1] = z->unit_dir[o2][1];
            right_foreign = 1;
        }
        /* cut-off centres p / tau; t along the cut-off segment, t_left / t_right along the legs */
        const real_t lcx = inv_tau * (z->point[o1][0] - px), lcy = inv_tau * (z->point[o1][1] - py);
        const real_t rcx = inv_tau * (z->point[o2][0] - px), rcy = inv_tau * (z->point[o2][1] - py);
        const real_t cvx = rcx - lcx, cvy = rcy - lcy;
        const int same = o1 == o2;
        const real_t t =
            same ? R(0.5) : ((vx - lcx) * cvx + (vy - lcy) * cvy) / (cvx * cvx + cvy * cvy);
        const real_t t_left = (vx - lcx) * left[0] + (vy - lcy) * left[1];
        const real_t t_right = (vx - rcx) * right[0] + (vy - rcy) * right[1];
        const real_t rt = r * inv_tau;
        if ((t < R(0.0) && t_left < R(0.0)) || (same && t_left < R(0.0) && t_right < R(0.0))) {
            real_t ux, uy; /* the left cut-off disc */
            normalize(vx - lcx, vy - lcy, &ux, &uy);
            put(&lines[n++], lcx + rt * ux, lcy + rt * uy, uy, -ux);
            continue;
        }
        if (t > R(1.0) && t_right < R(0.0)) {
            real_t ux, uy; /* the right cut-off disc */
            normalize(vx - rcx, vy - rcy, &ux, &uy);
            put(&lines[n++], rcx + rt * ux, rcy + rt * uy, uy, -ux);
            continue;
        }
        real_t d_cut = (real_t)INFINITY, d_left = (real_t)INFINITY, d_right = (real_t)INFINITY;
        if (!(t < R(0.0) || t > R(1.0) || same)) {
            const real_t wx = vx - (lcx + t * cvx), wy = vy - (lcy + t * cvy);
            d_cut = wx * wx + wy * wy;
        }
        if (!(t_left < R(0.0))) {
            const real_t wx = vx - (lcx + t_left * left[0]), wy = vy - (lcy + t_left * left[1]);
            d_left = wx * wx + wy * wy;
        }
        if (!(t_right < R(0.0))) {
            const real_t wx = vx - (rcx + t_right * right[0]), wy = vy - (rcy + t_right * right[1]);
            d_right = wx * wx + wy * wy;
        }
        if (d_cut <= d_left && d_cut <= d_right) {
            dx = -z->unit_dir[o1][0]; /* the cut-off line */
            dy = -z->unit_dir[o1][1];
            put(&lines[n++], lcx + rt * -dy, lcy + rt * dx, dx, dy);
            continue;
        }
        if (d_left <= d_right) {
            if (left_foreign) {
                continue;
            }
            put(&lines[n++], lcx + rt * -left[1], lcy + rt * left[0], left[0], left[1]);
            continue;
        }
        if (right_foreign) {
            continue;
        }
        dx = -right[0];
        dy = -right[1];
        put(&lines[n++], rcx + rt * -dy, rcy + rt * dx, dx, dy);
    }
    return n;
}

covey_status_t covey_safety_filter_zones(const covey_safety_config_t *cfg,
                                         const covey_zones_t *zones, const covey_track_t *own,
                                         const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                         int32_t n_nbrs, covey_safety_scratch_t *scratch,
                                         covey_safety_out_t *out)
{
    if (zones == NULL || zones->n_vertices == 0) {
        return covey_safety_filter(cfg, own, pref_vel_m_s, nbrs, n_nbrs, scratch, out);
    }
    if (cfg == NULL || own == NULL || scratch == NULL || out == NULL) {
        return covey_safety_filter(cfg, own, pref_vel_m_s, nbrs, n_nbrs, scratch, out);
    }
    covey_status_t st = covey_safety_config_check(cfg);
    if (st == COVEY_OK) {
        st = covey_track_check(own);
    }
    if (st != COVEY_OK) { /* the filter reports it, with its zero output */
        return covey_safety_filter(cfg, own, pref_vel_m_s, nbrs, n_nbrs, scratch, out);
    }
    /* zones padded like pairs: sigma_k x the own 1-sigma (policy/safety.py filter_one) */
    const float pad_m = cfg->sigma_k * own->pos_sigma_m;
    const int32_t n_hard = covey_zones_lines(zones, own, cfg->max_speed_m_s, pad_m, scratch->hard);
    return covey_safety_filter_hard(cfg, own, pref_vel_m_s, nbrs, n_nbrs, n_hard, scratch, out);
}

uint32_t covey_zones_bytes(void)
{
    return (uint32_t)sizeof(covey_zones_t);
}
