/*
 * covey_safety.c - ORCA half-planes and the incremental 2-D LP; see
 * covey_safety.h. A line-by-line port of policy/safety.py in float32; the
 * parity tests (tests/test_firmware_safety.py) compare the two on shared vectors.
 */
#include "covey_safety.h"

#include <math.h>
#include <stddef.h>

typedef covey_real_t real_t;
typedef covey_halfplane_t line_t;
#if COVEY_SAFETY_DOUBLE
#define R(x) ((double)(x))
#define R_SQRT sqrt
#define R_FABS fabs
#define R_FMIN fmin
#define R_FMAX fmax
#else
#define R(x) ((float)(x))
#define R_SQRT sqrtf
#define R_FABS fabsf
#define R_FMIN fminf
#define R_FMAX fmaxf
#endif

/* Guard of divisions and parallel-line tests; policy/safety.py EPS. */
#define COVEY_SAFETY_EPS R(1.0e-9)
#if COVEY_SAFETY_DOUBLE
#define R_COS cos
#define R_SIN sin
#define COINCIDENT_M 0.01
#else
#define R_COS cosf
#define R_SIN sinf
#define COINCIDENT_M COVEY_SAFETY_COINCIDENT_M
#endif

/*
 * Where a coincident neighbour is taken to be, as a unit (north, east) vector: one bearing per
 * unordered pair of ids, h = (lo 0x9E3779B1 xor hi 0x85EBCA77) mod 2^32, h ^= h >> 15,
 * bearing = 2 pi (h mod 2^16) / 2^16, seen from the lower id; the higher id sees the opposite.
 * policy/safety.py tie_direction computes the same integers.
 */
static void tie_direction(uint32_t own_id, uint32_t nbr_id, real_t *dn, real_t *de)
{
    const uint32_t lo = own_id < nbr_id ? own_id : nbr_id;
    const uint32_t hi = own_id < nbr_id ? nbr_id : own_id;
    uint32_t h = (lo * 0x9E3779B1u) ^ (hi * 0x85EBCA77u);
    h ^= h >> 15;
    const real_t bearing = R(h & 0xFFFFu) * R(6.283185307179586 / 65536.0);
    const real_t sign = own_id == lo ? R(1.0) : R(-1.0);
    *dn = sign * R_COS(bearing);
    *de = sign * R_SIN(bearing);
}


covey_safety_config_t covey_safety_defaults(float separation_m, float max_speed_m_s)
{
    covey_safety_config_t c;
    c.radius_m = separation_m;
    c.margin = 0.2f; /* policy/safety.py SafetyConfig.margin */
    c.time_horizon_s = 4.0f;
    c.dt_s = 0.1f;
    c.max_speed_m_s = max_speed_m_s;
    c.responsibility = 0.5f;
    c.sigma_k = 4.0f; /* policy/safety.py SIGMA_K */
    c.non_cooperative_radius_m = 0.0f;
    c.manned_radius_m = COVEY_SAFETY_MANNED_SEPARATION_M;
    c.recover_speed_share = COVEY_SAFETY_RECOVER_SPEED_SHARE;
    return c;
}

static int in_range(float x, float lo, float hi)
{
    return x >= lo && x <= hi;
}

covey_status_t covey_safety_config_check(const covey_safety_config_t *cfg)
{
    if (cfg == NULL) {
        return COVEY_ERR_NULL;
    }
    if (!isfinite(cfg->radius_m) || !isfinite(cfg->margin) || !isfinite(cfg->time_horizon_s) ||
        !isfinite(cfg->dt_s) || !isfinite(cfg->max_speed_m_s) || !isfinite(cfg->responsibility) ||
        !isfinite(cfg->sigma_k) || !isfinite(cfg->non_cooperative_radius_m) ||
        !isfinite(cfg->manned_radius_m) || !isfinite(cfg->recover_speed_share)) {
        return COVEY_ERR_NONFINITE;
    }
    if (!in_range(cfg->radius_m, COVEY_SAFETY_MIN_RADIUS_M, COVEY_SAFETY_MAX_RADIUS_M) ||
        !in_range(cfg->margin, 0.0f, COVEY_SAFETY_MAX_MARGIN) ||
        !in_range(cfg->time_horizon_s, COVEY_SAFETY_MIN_TIME_S, COVEY_SAFETY_MAX_TIME_S) ||
        !in_range(cfg->dt_s, COVEY_SAFETY_MIN_TIME_S, COVEY_SAFETY_MAX_TIME_S) ||
        !in_range(cfg->max_speed_m_s, COVEY_MIN_CRUISE_SPEED_M_S, COVEY_MAX_CRUISE_SPEED_M_S) ||
        !(cfg->responsibility > 0.0f && cfg->responsibility <= 1.0f) ||
        !in_range(cfg->sigma_k, 0.0f, COVEY_SAFETY_MAX_SIGMA_K) ||
        !(cfg->non_cooperative_radius_m == 0.0f ||
          in_range(cfg->non_cooperative_radius_m, COVEY_SAFETY_MIN_RADIUS_M,
                   COVEY_SAFETY_MAX_RADIUS_M)) ||
        !(cfg->manned_radius_m == 0.0f ||
          in_range(cfg->manned_radius_m, COVEY_SAFETY_MIN_RADIUS_M, COVEY_SAFETY_MAX_RADIUS_M)) ||
        !in_range(cfg->recover_speed_share, 0.0f, COVEY_SAFETY_MAX_RECOVER_SHARE)) {
        return COVEY_ERR_RANGE;
    }
    return COVEY_OK;
}

covey_status_t covey_track_check(const covey_track_t *t)
{
    if (t == NULL) {
        return COVEY_ERR_NULL;
    }
    if (!isfinite(t->pos_n_m) || !isfinite(t->pos_e_m) || !isfinite(t->vel_n_m_s) ||
        !isfinite(t->vel_e_m_s) || !isfinite(t->pos_sigma_m)) {
        return COVEY_ERR_NONFINITE;
    }
    if (fabsf(t->pos_n_m) > COVEY_MAX_ABS_POS_M || fabsf(t->pos_e_m) > COVEY_MAX_ABS_POS_M ||
        fabsf(t->vel_n_m_s) > COVEY_MAX_ABS_VEL_M_S || fabsf(t->vel_e_m_s) > COVEY_MAX_ABS_VEL_M_S ||
        !in_range(t->pos_sigma_m, 0.0f, COVEY_SAFETY_MAX_SIGMA_M)) {
        return COVEY_ERR_RANGE;
    }
    return COVEY_OK;
}

/* v / max(|v| / radius, 1), as lp2 computes it (so "changed" compares equal bits) */
static void clip_to_disc(const real_t v[2], real_t radius, real_t out[2])
{
    const real_t n = R_SQRT(v[0] * v[0] + v[1] * v[1]);
    if (n <= radius) {
        out[0] = v[0];
        out[1] = v[1];
    } else {
        out[0] = v[0] / n * radius;
        out[1] = v[1] / n * radius;
    }
}

/* det(a, b) = a_x b_y - a_y b_x */
static real_t det2(real_t ax, real_t ay, real_t bx, real_t by)
{
    return ax * by - ay * bx;
}

/*
 * The ORCA half-plane of one neighbour. p = p_j - p_i, v = v_i - v_j, r = radius (1 + margin):
 *   not overlapping (|p| > r): w = v - p / tau is v's offset from the cut-off circle centre;
 *     if v projects onto the cut-off circle (w.p < 0 and (w.p)^2 > r^2 |w|^2):
 *       u = (r / tau - |w|) w / |w|, the line is perpendicular to w;
 *     else onto the nearer leg l of the cone (tangent from the origin to the disc):
 *       u = (v.l) l - v, the line runs along l;
 *   overlapping: the same with the disc centred on p / dt, to separate within one period.
 *   point = v_own + responsibility u.
 */
/*
 * A non-cooperative pair (nc = 1) looks tau ahead (pair_horizon, not cfg's) and, on a collision
 * course (v inside the untruncated cone: v.p > 0 and |det(p, v)| < r |v|), always resolves on a
 * leg of the cone: the half-plane's normal is lateral, so the vehicle steps aside instead of
 * fleeing along the line of a faster intruder (policy/safety.py orca_lines). The leg keeps us
 * on our side of the neighbour's track when it is at least as fast as max_speed_m_s (else the
 * side v leans to; `kept_offset`); within COVEY_SAFETY_NC_SIDE_BIAS r of it, the right-hand leg
 * (north/east).
 */
/*
 * This vehicle's offset from a neighbour's track times its speed, m = det(p, v_j) (v_j = (jx, jy),
 * |v_j| = j_len), or, on the side m > 0 that the bias band would make it leave, where it will be
 * when the neighbour arrives alongside if that is further off: m - T det(v_own, v_j), T = along /
 * closing (0 when the neighbour is behind us or not gaining). A vehicle already leaving the
 * track on that side keeps it, and so does one within the band on the other side (m > -bias r
 * |v_j|) that escapes towards m > 0 faster than COVEY_SAFETY_NC_KEEP_SIDE_SPEED_FACTOR vmax: the
 * track line swung across it (policy/traffic_rules.py kept_offset).
 */
static real_t kept_offset(real_t px, real_t py, real_t jx, real_t jy, real_t j_len,
                          const covey_track_t *own, real_t r, real_t vmax)
{
    const real_t m = px * jy - py * jx;
    const real_t ox = R(own->vel_n_m_s), oy = R(own->vel_e_m_s);
    const real_t off_track = oy * jx - ox * jy; /* own speed towards m > 0, times |v_j| */
    if (m <= R(0.0) &&
        !(m > -R(COVEY_SAFETY_NC_SIDE_BIAS) * r * j_len &&
          off_track > R(COVEY_SAFETY_NC_KEEP_SIDE_SPEED_FACTOR) * vmax * j_len)) {
        return m;
    }
    const real_t jn = R_FMAX(j_len, COVEY_SAFETY_EPS);
    const real_t tx = jx / jn, ty = jy / jn;
    const real_t along = -(px * tx + py * ty);
    const real_t closing = j_len - (ox * tx + oy * ty);
    if (along <= R(0.0) || closing <= COVEY_SAFETY_EPS) {
        return m;
    }
    return R_FMAX(m, m + along / closing * off_track);
}

static void orca_line(const covey_safety_config_t *cfg, real_t r, real_t pad, real_t share,
                      real_t tau, int nc, real_t px, real_t py, real_t vx, real_t vy,
                      const covey_track_t *own, line_t *line)
{
    const real_t dist_sq = px * px + py * py;
    real_t dir_x, dir_y, u_x, u_y;
    if (nc && dist_sq <= r * r && px * vx + py * vy > R(0.0)) {
        /* already within r of it, closing, and it at least as fast as we are: fleeing along the
         * line cannot work, so v . n >= COVEY_SAFETY_NC_ESCAPE_SHARE max_speed, n off its track
         * on the step-aside side (policy/safety.py NC_ESCAPE_SHARE) */
        const real_t jx = R(own->vel_n_m_s) - vx, jy = R(own->vel_e_m_s) - vy;
        const real_t j_len = R_SQRT(jx * jx + jy * jy);
        if (j_len >= R(cfg->max_speed_m_s)) {
            const real_t jn = R_FMAX(j_len, COVEY_SAFETY_EPS);
            const real_t vmax = R(cfg->max_speed_m_s);
            const real_t sgn = kept_offset(px, py, jx, jy, j_len, own, r, vmax) <
                                       R(COVEY_SAFETY_NC_SIDE_BIAS) * r * j_len
                                   ? R(1.0)
                                   : R(-1.0);
            const real_t nx = sgn * jy / jn, ny = -sgn * jx / jn;
            const real_t tx = jx / jn, ty = jy / jn;
            real_t spd = R(COVEY_SAFETY_NC_ESCAPE_SHARE) * vmax;
            /* or what clears the berth before it arrives: off its track by `off` on the escape
             * side, `along` ahead of it on its track, it gaining `closing` (traffic_rules.py
             * clear_speed) */
            const real_t off = -(px * nx + py * ny);
            const real_t along = -(px * tx + py * ty);
            const real_t closing =
                j_len - (R(own->vel_n_m_s) * tx + R(own->vel_e_m_s) * ty);
            if (along > R(0.0) && closing > COVEY_SAFETY_EPS) {
                const real_t t_s = R_FMAX(along / closing, COVEY_SAFETY_EPS);
                /* up to COVEY_SAFETY_NC_CLEAR_SHARE of the lateral speed that, with the
                 * speed kept along its track (our own now, 0 to vmax), gains the most room
                 * before it arrives */
                const real_t speed =
                    R_FMIN(R(COVEY_SAFETY_NC_ESCAPE_SPEED_FACTOR) * vmax, R_FMAX(vmax, j_len));
                const real_t best = R_FMIN(vmax, speed * speed / R_FMAX(j_len, COVEY_SAFETY_EPS));
                const real_t ahead = R_FMIN(R_FMAX(j_len - closing, R(0.0)), best);
                const real_t cap = R(COVEY_SAFETY_NC_CLEAR_SHARE) *
                                   R_SQRT(R_FMAX(speed * speed - ahead * ahead, R(0.0)));
                spd = R_FMAX(spd, R_FMIN((r - off) / t_s, cap));
            }
            line->point[0] = spd * nx;
            line->point[1] = spd * ny;
            line->dir[0] = ny;
            line->dir[1] = -nx;
            return;
        }
    }
    if (dist_sq <= r * r) {
        real_t inv_dt = R(1.0) / R(cfg->dt_s);
        const real_t d = R_SQRT(dist_sq);
        if (cfg->recover_speed_share > 0.0f && pad > R(0.0) && d >= r - pad) {
            /* inside the uncertainty padding only: part at what vehicles can, not within one
             * dt (policy/safety.py RECOVER_SPEED_SHARE) */
            const real_t gap = r - d;
            const real_t rec = R(cfg->recover_speed_share) * R(cfg->max_speed_m_s);
            if (gap * inv_dt > rec) {
                inv_dt = rec / gap;
            }
        }
        const real_t cx = vx - inv_dt * px;
        const real_t cy = vy - inv_dt * py;
        const real_t c_len = R_SQRT(R_FMAX(cx * cx + cy * cy, COVEY_SAFETY_EPS));
        const real_t ucx = cx / c_len;
        const real_t ucy = cy / c_len;
        dir_x = ucy;
        dir_y = -ucx;
        u_x = (r * inv_dt - c_len) * ucx;
        u_y = (r * inv_dt - c_len) * ucy;
    } else {
        const real_t wx = vx - px / tau;
        const real_t wy = vy - py / tau;
        const real_t w_len_sq = wx * wx + wy * wy;
        const real_t dot1 = wx * px + wy * py;
        int left = px * wy - py * wx > R(0.0);
        int steer = 0;
        if (nc) {
            const real_t det_pv = px * vy - py * vx; /* = det(p, w) */
            const real_t v_len = R_SQRT(vx * vx + vy * vy);
            steer = px * vx + py * vy > R(0.0) && R_FABS(det_pv) < r * v_len;
            if (steer) {
                /* off the neighbour's own track (p x v_j) when it is at least as fast as we
                 * are, else the side v leans to; within the bias band, the right-hand leg */
                const real_t jx = R(own->vel_n_m_s) - vx, jy = R(own->vel_e_m_s) - vy;
                const real_t j_len = R_SQRT(jx * jx + jy * jy);
                const real_t vmax = R(cfg->max_speed_m_s);
                if (j_len >= vmax) {
                    left = kept_offset(px, py, jx, jy, j_len, own, r, vmax) <
                           R(COVEY_SAFETY_NC_SIDE_BIAS) * r * j_len;
                } else {
                    left = -det_pv < R(COVEY_SAFETY_NC_SIDE_BIAS) * r * v_len;
                }
            }
        }
        if (!steer && dot1 < R(0.0) && dot1 * dot1 > r * r * w_len_sq) {
            const real_t w_len = R_SQRT(R_FMAX(w_len_sq, COVEY_SAFETY_EPS));
            const real_t ux_c = wx / w_len;
            const real_t uy_c = wy / w_len;
            dir_x = uy_c;
            dir_y = -ux_c;
            u_x = (r / tau - w_len) * ux_c;
            u_y = (r / tau - w_len) * uy_c;
        } else {
            /* leg = sqrt(|p|^2 - r^2); left leg when det(p, w) > 0, else the right one */
            const real_t leg = R_SQRT(R_FMAX(dist_sq - r * r, R(0.0)));
            const real_t inv = R(1.0) / R_FMAX(dist_sq, COVEY_SAFETY_EPS);
            real_t lx, ly;
            if (left) {
                lx = (px * leg - py * r) * inv;
                ly = (px * r + py * leg) * inv;
            } else {
                lx = -(px * leg + py * r) * inv;
                ly = -(-px * r + py * leg) * inv;
            }
            const real_t dot2 = vx * lx + vy * ly;
            dir_x = lx;
            dir_y = ly;
            u_x = dot2 * lx - vx;
            u_y = dot2 * ly - vy;
        }
    }
    const real_t k = share;
    line->point[0] = R(own->vel_n_m_s) + k * u_x;
    line->point[1] = R(own->vel_e_m_s) + k * u_y;
    line->dir[0] = dir_x;
    line->dir[1] = dir_y;
}

/*
 * Optimum on line n, subject to lines [0, n) and |v| <= radius (the speed disc).
 * Line n is point + t dir; the disc leaves t in [-d.p - s, -d.p + s] with
 * s^2 = (d.p)^2 + radius^2 - |p|^2; every earlier line cuts that interval at
 * t = det(e, p - q) / det(d, e). Returns 0 when the interval is empty.
 */
static int lp1(const line_t *lines, int32_t n, real_t radius, const real_t opt[2],
               int direction_opt, real_t result[2])
{
    const real_t px = lines[n].point[0], py = lines[n].point[1];
    const real_t dx = lines[n].dir[0], dy = lines[n].dir[1];
    const real_t dot = px * dx + py * dy;
    const real_t disc = dot * dot + radius * radius - (px * px + py * py);
    if (disc < R(0.0)) {
        return 0;
    }
    const real_t sq = R_SQRT(disc);
    real_t t_left = -dot - sq;
    real_t t_right = -dot + sq;
    for (int32_t i = 0; i < n; ++i) {
        const real_t qx = lines[i].point[0], qy = lines[i].point[1];
        const real_t ex = lines[i].dir[0], ey = lines[i].dir[1];
        const real_t denom = det2(dx, dy, ex, ey);
        const real_t numer = det2(ex, ey, px - qx, py - qy);
        if (R_FABS(denom) <= COVEY_SAFETY_EPS) {
            if (numer < R(0.0)) {
                return 0; /* parallel and entirely on the forbidden side */
            }
            continue;
        }
        const real_t t = numer / denom;
        if (denom >= R(0.0)) {
            t_right = R_FMIN(t_right, t);
        } else {
            t_left = R_FMAX(t_left, t);
        }
        if (t_left > t_right) {
            return 0;
        }
    }
    real_t t;
    if (direction_opt) {
        t = (opt[0] * dx + opt[1] * dy > R(0.0)) ? t_right : t_left;
    } else {
        /* projection of opt onto the line, clamped to the interval */
        t = R_FMIN(R_FMAX(dx * (opt[0] - px) + dy * (opt[1] - py), t_left), t_right);
    }
    result[0] = px + t * dx;
    result[1] = py + t * dy;
    return 1;
}

/*
 * Incremental 2-D LP (Seidel-style, in index order): the point of the disc that
 * is closest to opt (or farthest along the direction opt) inside lines [0, count).
 * Returns count on success, else the first line that made it infeasible; result
 * then holds the optimum of the lines before it.
 */
static int32_t lp2(const line_t *lines, int32_t count, real_t radius, const real_t opt[2],
                   int direction_opt, real_t result[2])
{
    if (direction_opt) {
        result[0] = opt[0] * radius;
        result[1] = opt[1] * radius;
    } else {
        clip_to_disc(opt, radius, result);
    }
    for (int32_t i = 0; i < count; ++i) {
        const line_t *l = &lines[i];
        if (det2(l->dir[0], l->dir[1], l->point[0] - result[0], l->point[1] - result[1]) > R(0.0)) {
            real_t tmp[2];
            if (!lp1(lines, i, radius, opt, direction_opt, tmp)) {
                return i;
            }
            result[0] = tmp[0];
            result[1] = tmp[1];
        }
    }
    return count;
}

/*
 * Fallback when infeasible: minimise the largest violation max_i det(d_i, p_i - v).
 * For each line i still violated by more than the current worst, solve a 2-D LP in
 * the space of lines [0, i) projected onto line i (their bisectors with it),
 * pushing as far as possible along the normal (-d_y, d_x).
 */
static void lp3(const line_t *lines, int32_t count, int32_t begin, real_t radius,
                line_t *proj, real_t result[2], int32_t n_hard)
{
    /* lines [0, n_hard) are hard: copied into every projected program as they are */
    real_t distance = R(0.0);
    for (int32_t i = begin > n_hard ? begin : n_hard; i < count; ++i) {
        const real_t px = lines[i].point[0], py = lines[i].point[1];
        const real_t dx = lines[i].dir[0], dy = lines[i].dir[1];
        if (det2(dx, dy, px - result[0], py - result[1]) <= distance) {
            continue;
        }
        int32_t n_proj = 0;
        for (; n_proj < n_hard; ++n_proj) {
            proj[n_proj] = lines[n_proj];
        }
        for (int32_t j = n_hard; j < i; ++j) {
            const real_t qx = lines[j].point[0], qy = lines[j].point[1];
            const real_t ex = lines[j].dir[0], ey = lines[j].dir[1];
            const real_t determinant = det2(dx, dy, ex, ey);
            real_t ptx, pty;
            if (R_FABS(determinant) <= COVEY_SAFETY_EPS) {
                if (dx * ex + dy * ey > R(0.0)) {
                    continue; /* same direction: line j adds nothing */
                }
                ptx = R(0.5) * (px + qx);
                pty = R(0.5) * (py + qy);
            } else {
                const real_t t = det2(ex, ey, px - qx, py - qy) / determinant;
                ptx = px + t * dx;
                pty = py + t * dy;
            }
            const real_t nx = ex - dx;
            const real_t ny = ey - dy;
            const real_t nn = R_FMAX(R_SQRT(nx * nx + ny * ny), COVEY_SAFETY_EPS);
            proj[n_proj].point[0] = ptx;
            proj[n_proj].point[1] = pty;
            proj[n_proj].dir[0] = nx / nn;
            proj[n_proj].dir[1] = ny / nn;
            ++n_proj;
        }
        const real_t normal[2] = {-dy, dx};
        real_t candidate[2];
        if (lp2(proj, n_proj, radius, normal, 1, candidate) >= n_proj) {
            result[0] = candidate[0];
            result[1] = candidate[1];
        }
        distance = det2(dx, dy, px - result[0], py - result[1]);
    }
}

static covey_status_t fail(covey_safety_out_t *out, covey_status_t status)
{
    if (out != NULL) {
        out->vel_n_m_s = 0.0f;
        out->vel_e_m_s = 0.0f;
    }
    return status;
}

covey_status_t covey_safety_filter(const covey_safety_config_t *cfg, const covey_track_t *own,
                                   const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                   int32_t n_nbrs, covey_safety_scratch_t *scratch,
                                   covey_safety_out_t *out)
{
    return covey_safety_filter_hard(cfg, own, pref_vel_m_s, nbrs, n_nbrs, 0, scratch, out);
}

covey_status_t covey_safety_filter_hard(const covey_safety_config_t *cfg, const covey_track_t *own,
                                        const float pref_vel_m_s[2], const covey_track_t *nbrs,
                                        int32_t n_nbrs, int32_t n_hard,
                                        covey_safety_scratch_t *scratch, covey_safety_out_t *out)
{
    if (out != NULL) {
        out->n_lines = 0;
        out->changed = 0;
        out->infeasible = 0;
    }
    if (cfg == NULL || own == NULL || pref_vel_m_s == NULL || scratch == NULL || out == NULL ||
        (nbrs == NULL && n_nbrs > 0)) {
        return fail(out, COVEY_ERR_NULL);
    }
    covey_status_t st = covey_safety_config_check(cfg);
    if (st != COVEY_OK) {
        return fail(out, st);
    }
    if (n_nbrs < 0 || n_nbrs > COVEY_MAX_INPUTS) {
        return fail(out, COVEY_ERR_RANGE);
    }
    st = covey_track_check(own);
    if (st != COVEY_OK) {
        return fail(out, st);
    }
    if (!isfinite(pref_vel_m_s[0]) || !isfinite(pref_vel_m_s[1])) {
        return fail(out, COVEY_ERR_NONFINITE);
    }
    if (fabsf(pref_vel_m_s[0]) > COVEY_MAX_ABS_VEL_M_S ||
        fabsf(pref_vel_m_s[1]) > COVEY_MAX_ABS_VEL_M_S) {
        return fail(out, COVEY_ERR_RANGE);
    }
    for (int32_t i = 0; i < n_nbrs; ++i) {
        st = covey_track_check(&nbrs[i]);
        if (st != COVEY_OK) {
            return fail(out, st);
        }
    }

    /* neighbours that cannot meet us within the horizon add no line: |p| >= reach (see
     * covey_safety.h: r and share per pair) */
    const real_t one_margin = R(1.0) + R(cfg->margin);
    const real_t vmax = R(cfg->max_speed_m_s);
    const real_t tau = R(cfg->time_horizon_s);
    const real_t nc_base = cfg->non_cooperative_radius_m > 0.0f ? R(cfg->non_cooperative_radius_m)
                                                               : R(cfg->radius_m);
    const real_t manned_base = cfg->manned_radius_m > 0.0f ? R(cfg->manned_radius_m) : nc_base;
    const real_t s_own = R(own->pos_sigma_m);
    if (n_hard < 0 || n_hard > COVEY_SAFETY_MAX_HARD_LINES) {
        return fail(out, COVEY_ERR_RANGE);
    }
    int32_t n_lines = 0;
    for (; n_lines < n_hard; ++n_lines) {
        scratch->lines[n_lines] = scratch->hard[n_lines];
    }
    /* two passes: the non-cooperative neighbours' lines first, hard after the zones' (a crowd
     * that leaves no velocity meeting every line relaxes the covey neighbours', who avoid too,
     * never the line of traffic that will not: policy/safety.py _solve_nc_hard), then the rest */
    int32_t n_hard_all = n_hard;
    /* the fastest non-cooperative track with a line: its speed and unit velocity */
    real_t nc_speed = R(0.0), nc_tn = R(0.0), nc_te = R(0.0);
    /* the ahead rule: the nearest escaping track this vehicle is ahead of (policy/traffic_rules.py
     * ahead_track): its distance squared (-1: none) and unit velocity */
    real_t ahead_d = R(-1.0), ahead_tn = R(0.0), ahead_te = R(0.0);
    int32_t n_opt = 0; /* the optional lines: the track line, the ahead line */
    for (int32_t pass = 1; pass >= 0; --pass) {
        if (pass == 0) {
            if (nc_speed > vmax) {
                /* hard too: no faster than vmax along its track (v . t <= vmax), so that the
                 * escape speed takes the vehicle off the track, never races it along it
                 * (policy/traffic_rules.py escape_lines) */
                line_t *l = &scratch->lines[n_lines++];
                l->point[0] = vmax * nc_tn;
                l->point[1] = vmax * nc_te;
                l->dir[0] = -nc_te;
                l->dir[1] = nc_tn;
                ++n_opt;
            }
            if (ahead_d >= R(0.0)) {
                /* no motion back along the track of the neighbour it escapes while ahead of it
                 * (v . t >= 0): the closing speed stays the neighbour's own */
                line_t *l = &scratch->lines[n_lines++];
                l->point[0] = R(0.0);
                l->point[1] = R(0.0);
                l->dir[0] = ahead_te;
                l->dir[1] = -ahead_tn;
                ++n_opt;
            }
            n_hard_all = n_lines;
        }
        for (int32_t i = 0; i < n_nbrs; ++i) {
            const int nc = nbrs[i].non_cooperative != 0u;
            if (nc != pass) {
                continue;
            }
            real_t px = R(nbrs[i].pos_n_m) - R(own->pos_n_m);
            real_t py = R(nbrs[i].pos_e_m) - R(own->pos_e_m);
            const real_t s_nbr = R(nbrs[i].pos_sigma_m);
            const real_t base = !nc ? R(cfg->radius_m)
                                : nbrs[i].non_cooperative == COVEY_TRACK_MANNED ? manned_base
                                                                                 : nc_base;
            const real_t pad = R(cfg->sigma_k) * R_SQRT(s_own * s_own + s_nbr * s_nbr);
            const real_t r = base * one_margin + pad;
            const real_t share = nc ? R(1.0) : R(cfg->responsibility);
            /* a non-cooperative track as planned against: NC_SPEED_MARGIN faster than reported
             * (policy/traffic_rules.py planned_velocity) */
            const real_t vscale = nc ? R(1.0) + R(COVEY_SAFETY_NC_SPEED_MARGIN) : R(1.0);
            const real_t nvn = vscale * R(nbrs[i].vel_n_m_s);
            const real_t nve = vscale * R(nbrs[i].vel_e_m_s);
            const real_t vx = R(own->vel_n_m_s) - nvn;
            const real_t vy = R(own->vel_e_m_s) - nve;
            real_t reach = r + R(2.0) * vmax * tau;
            real_t tau_j = tau;
            if (nc) {
                /* tau_j = clip((r / vmax) (|v| / vmax), tau, cap) (policy/traffic_rules.py
                 * pair_horizon_s): time to step one pair distance aside, times how much faster the
                 * pair closes than we move; cap = max(factor tau, r / (escape vmax) + tau), the
                 * time to leave a wide berth (a manned aircraft's) at the escape speed */
                const real_t cap =
                    R_FMAX(R(COVEY_SAFETY_NC_MAX_HORIZON_FACTOR) * tau,
                           r / (R(COVEY_SAFETY_NC_ESCAPE_SPEED_FACTOR) * vmax) + tau);
                tau_j = r / vmax * (R_SQRT(vx * vx + vy * vy) / vmax);
                tau_j = R_FMIN(R_FMAX(tau_j, tau), cap);
                reach = r + (vmax + R_FMAX(vmax, R_SQRT(nvn * nvn + nve * nve))) * tau_j;
            }
            if (px * px + py * py >= reach * reach) {
                continue;
            }
            /* coincident: no direction in p, so the pair of ids gives one (tie_direction) */
            if (px * px + py * py < R(COINCIDENT_M) * R(COINCIDENT_M) && own->id != 0u &&
                nbrs[i].id != 0u && own->id != nbrs[i].id) {
                real_t dn, de;
                tie_direction(own->id, nbrs[i].id, &dn, &de);
                px = dn * R(COINCIDENT_M);
                py = de * R(COINCIDENT_M);
            }
            if (nc) {
                const real_t speed = R_SQRT(nvn * nvn + nve * nve);
                if (speed > nc_speed) {
                    nc_speed = speed;
                    nc_tn = nvn / speed;
                    nc_te = nve / speed;
                }
                const real_t d_sq = px * px + py * py;
                const real_t jx = R(own->vel_n_m_s) - vx, jy = R(own->vel_e_m_s) - vy;
                const real_t j_len = R_SQRT(jx * jx + jy * jy);
                if (d_sq <= r * r && px * vx + py * vy > R(0.0) && j_len >= vmax &&
                    px * jx + py * jy < R(0.0) && (ahead_d < R(0.0) || d_sq < ahead_d)) {
                    const real_t jn = R_FMAX(j_len, COVEY_SAFETY_EPS);
                    ahead_d = d_sq;
                    ahead_tn = jx / jn;
                    ahead_te = jy / jn;
                }
            }
            orca_line(cfg, r, pad, share, tau_j, nc, px, py, vx, vy, own,
                      &scratch->lines[n_lines++]);
        }
    }

    const real_t pref[2] = {R(pref_vel_m_s[0]), R(pref_vel_m_s[1])};
    /* a faster non-cooperative track's line: the speed disc grows to its speed, at most
     * NC_ESCAPE_SPEED_FACTOR vmax, to let the vehicle out of its way (policy/traffic_rules.py
     * escape_speed_m_s) */
    const real_t disc =
        R_FMIN(R(COVEY_SAFETY_NC_ESCAPE_SPEED_FACTOR) * vmax, R_FMAX(vmax, nc_speed));
    real_t v[2];
    int32_t failed = lp2(scratch->lines, n_lines, disc, pref, 0, v);
    if (failed < n_hard_all && n_opt > 0) {
        /* the hard lines cannot all be met: the optional lines go first (orca_lp.py
         * solve_lines n_optional); they are the last hard lines */
        for (int32_t i = n_hard_all; i < n_lines; ++i) {
            scratch->lines[i - n_opt] = scratch->lines[i];
        }
        n_hard_all -= n_opt;
        n_lines -= n_opt;
        n_opt = 0;
        failed = lp2(scratch->lines, n_lines, disc, pref, 0, v);
    }
    if (failed < n_lines) {
        lp3(scratch->lines, n_lines, failed, disc, scratch->proj, v,
            failed >= n_hard_all ? n_hard_all : 0);
        out->infeasible = 1;
    }
    real_t start[2]; /* what lp2 starts from: the preference clipped to the speed disc */
    clip_to_disc(pref, disc, start);
    out->changed = (v[0] != start[0] || v[1] != start[1]) ? 1 : 0;
    out->n_lines = n_lines - n_opt; /* the zones' and the neighbours' */
    /* a net under rounding: the output never leaves the speed disc, never non-finite */
    real_t clipped[2];
    clip_to_disc(v, disc, clipped);
    const float v_n = (float)clipped[0];
    const float v_e = (float)clipped[1];
    if (!isfinite(v_n) || !isfinite(v_e)) {
        return fail(out, COVEY_ERR_NONFINITE); /* unreachable with checked inputs; never fly it */
    }
    out->vel_n_m_s = v_n;
    out->vel_e_m_s = v_e;
    return COVEY_OK;
}

uint32_t covey_safety_scratch_bytes(void)
{
    return (uint32_t)sizeof(covey_safety_scratch_t);
}
