/*
 * covey_policy.c - see covey_policy.h and docs/POLICY_SPEC.md.
 *
 * All arithmetic is float32. The only globals are the const weights of the
 * generated header, instantiated here (COVEY_WEIGHTS_IMPLEMENTATION).
 */
#define COVEY_WEIGHTS_IMPLEMENTATION
#include "covey_policy.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

#define COVEY_PI_F 3.14159265358979f
#define COVEY_TWO_PI_F 6.28318530717959f

/* ---- input checks ------------------------------------------------------- */

/* 0 if finite and |x| <= bound, else the fault. isfinite first: NaN fails every compare. */
static covey_status_t check_abs(float x, float bound)
{
    if (!isfinite(x)) {
        return COVEY_ERR_NONFINITE;
    }
    return (fabsf(x) <= bound) ? COVEY_OK : COVEY_ERR_RANGE;
}

covey_status_t covey_config_check(const covey_config_t *cfg)
{
    if (cfg == NULL) {
        return COVEY_ERR_NULL;
    }
    if (!isfinite(cfg->separation_m) || !isfinite(cfg->cruise_speed_m_s)) {
        return COVEY_ERR_NONFINITE;
    }
    if (!(cfg->separation_m >= COVEY_MIN_SEPARATION_M && cfg->separation_m <= COVEY_MAX_SEPARATION_M)) {
        return COVEY_ERR_RANGE;
    }
    if (!(cfg->cruise_speed_m_s >= COVEY_MIN_CRUISE_SPEED_M_S &&
          cfg->cruise_speed_m_s <= COVEY_MAX_CRUISE_SPEED_M_S)) {
        return COVEY_ERR_RANGE;
    }
    if (cfg->max_neighbours < 0 || cfg->max_neighbours > COVEY_MAX_NEIGHBOURS) {
        return COVEY_ERR_RANGE;
    }
    return COVEY_OK;
}

/* Position and heading of a vehicle: non-finite first, then range. */
static covey_status_t check_vehicle_fields(const covey_vehicle_t *v)
{
    covey_status_t s_n = check_abs(v->pos_n_m, COVEY_MAX_ABS_POS_M);
    covey_status_t s_e = check_abs(v->pos_e_m, COVEY_MAX_ABS_POS_M);
    covey_status_t s_h = check_abs(v->heading_rad, COVEY_MAX_ABS_HEADING_RAD);
    if (s_n == COVEY_ERR_NONFINITE || s_e == COVEY_ERR_NONFINITE || s_h == COVEY_ERR_NONFINITE) {
        return COVEY_ERR_NONFINITE;
    }
    if (s_n != COVEY_OK || s_e != COVEY_OK || s_h != COVEY_OK) {
        return COVEY_ERR_RANGE;
    }
    return COVEY_OK;
}

/* ---- geometry ------------------------------------------------------------- */

/* wrap(a) = a - 2 pi floor((a + pi) / 2 pi), in [-pi, pi) (as the spec's mod form). */
static float wrap_rad(float a)
{
    float w = a - COVEY_TWO_PI_F * floorf((a + COVEY_PI_F) / COVEY_TWO_PI_F);
    /* float rounding can land exactly on +pi; the interval is half-open */
    return (w >= COVEY_PI_F) ? w - COVEY_TWO_PI_F : w;
}

/*
 * Neighbour tuple and encoding, policy units (r = p_j - p_i in metres, k = 3 / separation):
 *   d      = k |r| / dist_scale
 *   psi_ij = wrap(atan2(r_e, r_n) - h_i)        bearing of j from i's heading
 *   psi_ji = wrap(h_j - atan2(-r_e, -r_n))      j's heading against the line of sight j -> i
 *   paper:  x = [d, psi_ij, |psi_ji|]
 *   sincos: x = [d, sin psi_ij, cos psi_ij, sin psi_ji, cos psi_ji]
 */
static void encode_neighbour(const covey_vehicle_t *own, const covey_vehicle_t *nbr, float k_per_m,
                             float *x)
{
    float r_n = nbr->pos_n_m - own->pos_n_m;
    float r_e = nbr->pos_e_m - own->pos_e_m;
    float d = k_per_m * sqrtf(r_n * r_n + r_e * r_e) / COVEY_W_DIST_SCALE;
    float psi_ij = wrap_rad(atan2f(r_e, r_n) - own->heading_rad);
    float psi_ji = wrap_rad(nbr->heading_rad - atan2f(-r_e, -r_n));
#if COVEY_W_ENCODING_SINCOS
    x[0] = d;
    x[1] = sinf(psi_ij);
    x[2] = cosf(psi_ij);
    x[3] = sinf(psi_ji);
    x[4] = cosf(psi_ji);
#else
    x[0] = d;
    x[1] = psi_ij;
    x[2] = fabsf(psi_ji);
#endif
}

/* psi_D = wrap(atan2(g_e - p_e, g_n - p_n) - h); paper: [psi_D], sincos: [sin, cos]. */
static void encode_goal(const covey_vehicle_t *own, const covey_goal_t *goal, float *g)
{
    float psi_d = wrap_rad(atan2f(goal->pos_e_m - own->pos_e_m, goal->pos_n_m - own->pos_n_m) -
                           own->heading_rad);
#if COVEY_W_ENCODING_SINCOS
    g[0] = sinf(psi_d);
    g[1] = cosf(psi_d);
#else
    g[0] = psi_d;
#endif
}

/* ---- ordering --------------------------------------------------------------- */

/*
 * Stable insertion sorts of index lists (n <= COVEY_MAX_INPUTS, so O(n^2) is a
 * few thousand compares). Strict comparisons keep equal keys in their order.
 */
static void sort_by_dist_asc(int16_t *idx, int32_t n, const float *dist)
{
    for (int32_t a = 1; a < n; ++a) {
        int16_t v = idx[a];
        int32_t b = a - 1;
        while (b >= 0 && dist[idx[b]] > dist[v]) {
            idx[b + 1] = idx[b];
            --b;
        }
        idx[b + 1] = v;
    }
}

static void sort_by_dist_desc(int16_t *idx, int32_t n, const float *dist)
{
    for (int32_t a = 1; a < n; ++a) {
        int16_t v = idx[a];
        int32_t b = a - 1;
        while (b >= 0 && dist[idx[b]] < dist[v]) {
            idx[b + 1] = idx[b];
            --b;
        }
        idx[b + 1] = v;
    }
}

static void sort_by_index(int16_t *idx, int32_t n)
{
    for (int32_t a = 1; a < n; ++a) {
        int16_t v = idx[a];
        int32_t b = a - 1;
        while (b >= 0 && idx[b] > v) {
            idx[b + 1] = idx[b];
            --b;
        }
        idx[b + 1] = v;
    }
}

/* ---- network ---------------------------------------------------------------- */

/*
 * e^x without libm, in plain float arithmetic that a compiler vectorises
 * (glibc's expf is a scalar call; newlib's costs 41 Cortex-M7 instructions):
 *   x = k ln2 + r, |r| <= ln2 / 2, k = round(x / ln2) by the 1.5 * 2^23 shifter;
 *   e^r = 1 + r + r^2 P(r), P the Cephes expf polynomial (error about 1 ulp);
 *   2^k built in the exponent bits.
 * x is clamped to [-87, 88] first, so 2^k stays a normal float and nothing
 * overflows: sigma and tanh below still saturate to 0 / 1 / -1 exactly in float32.
 */
#if defined(__arm__) && !defined(COVEY_EXP_POLY)
/* Cortex-M: no vector unit to feed, and newlib's expf takes fewer instructions than
 * the polynomial (QEMU count: 1.21 M vs 1.25 M per N = 20 evaluation). It overflows to
 * +inf and underflows to 0, which sigma and tanh below turn into exact 0 / 1 / -1. */
static float exp_f(float x)
{
    return expf(x);
}
#else
static float exp_f(float x)
{
    const float shifter = 12582912.0f; /* 1.5 * 2^23: adding it rounds to an integer */
    x = (x < -87.0f) ? -87.0f : x;
    x = (x > 88.0f) ? 88.0f : x;
    float kf = x * 1.44269504088896341f + shifter;
    int32_t ki;
    memcpy(&ki, &kf, sizeof ki);
    ki -= 0x4B400000; /* the integer k, from the low mantissa bits */
    kf -= shifter;
    float r = x - kf * 0.693359375f; /* ln2 in two parts (Cody-Waite) */
    r = r - kf * -2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    const int32_t bits = (ki + 127) * 8388608; /* (k + 127) << 23 */
    float scale;
    memcpy(&scale, &bits, sizeof scale);
    return p * scale;
}
#endif

/*
 *   sigma(x) = 1 / (1 + e^-x)
 *   tanh(x)  = 1 - 2 / (e^{2x} + 1)
 * The absolute error stays near float32 epsilon, which is the error that
 * matters inside the network (parity tests check it against numpy).
 */
static float sigmoidf(float x)
{
    return 1.0f / (1.0f + exp_f(-x));
}

static float tanh_f(float x)
{
    return 1.0f - 2.0f / (exp_f(2.0f * x) + 1.0f);
}

/* acc + a b, fused into one VFMA where the FPU has it (Cortex-M7 fpv5). */
#if defined(__ARM_FEATURE_FMA)
#define COVEY_MAC(acc, a, b) __builtin_fmaf((a), (b), (acc))
#else
#define COVEY_MAC(acc, a, b) ((acc) + (a) * (b))
#endif

/*
 * y[r] += sum_k W[r][k] x[k] for r < rows, from W^T (cols x rows, input-major):
 * eight inputs at a time, y[r] += w0[r] x0 + w1[r] x1 + ... + w7[r] x7, then four, then one.
 * The inner loop runs over contiguous r with no dependence between rows, so a
 * host compiler vectorises it at -O3 without reassociating anything (the sum
 * order per row is k = 0, 1, 2, ... as in a plain dot product); on a Cortex-M7
 * each y load/store serves eight multiply-adds (2.3 instructions per multiply-add).
 */
static void matvec_acc(const float *restrict wt, const float *restrict x, int32_t rows,
                       int32_t cols, float *restrict y)
{
    int32_t k = 0;
    for (; k + 8 <= cols; k += 8) {
        const float *w0 = wt + (size_t)k * (size_t)rows;
        const float x0 = x[k], x1 = x[k + 1], x2 = x[k + 2], x3 = x[k + 3];
        const float x4 = x[k + 4], x5 = x[k + 5], x6 = x[k + 6], x7 = x[k + 7];
        for (int32_t r = 0; r < rows; ++r) {
            float acc = y[r];
            acc = COVEY_MAC(acc, w0[r], x0);
            acc = COVEY_MAC(acc, w0[rows + r], x1);
            acc = COVEY_MAC(acc, w0[2 * rows + r], x2);
            acc = COVEY_MAC(acc, w0[3 * rows + r], x3);
            acc = COVEY_MAC(acc, w0[4 * rows + r], x4);
            acc = COVEY_MAC(acc, w0[5 * rows + r], x5);
            acc = COVEY_MAC(acc, w0[6 * rows + r], x6);
            acc = COVEY_MAC(acc, w0[7 * rows + r], x7);
            y[r] = acc;
        }
    }
    for (; k + 4 <= cols; k += 4) {
        const float *w0 = wt + (size_t)k * (size_t)rows;
        const float x0 = x[k], x1 = x[k + 1], x2 = x[k + 2], x3 = x[k + 3];
        for (int32_t r = 0; r < rows; ++r) {
            float acc = y[r];
            acc = COVEY_MAC(acc, w0[r], x0);
            acc = COVEY_MAC(acc, w0[rows + r], x1);
            acc = COVEY_MAC(acc, w0[2 * rows + r], x2);
            acc = COVEY_MAC(acc, w0[3 * rows + r], x3);
            y[r] = acc;
        }
    }
    for (; k < cols; ++k) {
        const float *wk = wt + (size_t)k * (size_t)rows;
        const float xk = x[k];
        for (int32_t r = 0; r < rows; ++r) {
            y[r] = COVEY_MAC(y[r], wk[r], xk);
        }
    }
}

/*
 * One LSTM layer (torch nn.LSTM, gate rows i, f, g, o) from h = c = 0:
 *   [I F G O] = W_ih x_t + W_hh h_{t-1} + b          (b = b_ih + b_hh)
 *   c_t = sigma(F) c_{t-1} + sigma(I) tanh(G)
 *   h_t = sigma(O) tanh(c_t)
 * then the head on z = [tanh(h_T), goal]: z <- tanh(W_k z + b_k) for each layer,
 * and a = z / max(|z|, 1).
 */
static void run_network(const float *seq, int32_t n_steps, const float *goal_feat,
                        covey_scratch_t *s, float action[2])
{
    const int32_t H = COVEY_HIDDEN;
    const int32_t X = COVEY_INPUT;
    for (int32_t j = 0; j < H; ++j) {
        s->h[j] = 0.0f;
        s->c[j] = 0.0f;
    }
    for (int32_t t = 0; t < n_steps; ++t) {
        for (int32_t r = 0; r < 4 * H; ++r) {
            s->gates[r] = covey_w_lstm_b[r];
        }
        matvec_acc(covey_w_lstm_ih_t, seq + (size_t)t * (size_t)X, 4 * H, X, s->gates);
        if (t > 0) { /* h_0 = 0: the recurrent product vanishes on the first step */
            matvec_acc(covey_w_lstm_hh_t, s->h, 4 * H, H, s->gates);
        }
        for (int32_t j = 0; j < H; ++j) {
            const float i_g = sigmoidf(s->gates[j]);
            const float f_g = sigmoidf(s->gates[H + j]);
            const float g_g = tanh_f(s->gates[2 * H + j]);
            const float o_g = sigmoidf(s->gates[3 * H + j]);
            s->c[j] = f_g * s->c[j] + i_g * g_g;
            s->h[j] = o_g * tanh_f(s->c[j]);
        }
    }

    float *z_in = s->z[0];
    float *z_out = s->z[1];
    for (int32_t j = 0; j < H; ++j) {
        z_in[j] = tanh_f(s->h[j]);
    }
    for (int32_t j = 0; j < COVEY_GOAL; ++j) {
        z_in[H + j] = goal_feat[j];
    }
    for (int32_t layer = 0; layer < COVEY_W_HEAD_LAYERS; ++layer) {
        const int32_t n_out = covey_w_head_out[layer];
        for (int32_t r = 0; r < n_out; ++r) {
            z_out[r] = covey_w_head_b[layer][r];
        }
        matvec_acc(covey_w_head_wt[layer], z_in, n_out, covey_w_head_in[layer], z_out);
        for (int32_t r = 0; r < n_out; ++r) {
            z_out[r] = tanh_f(z_out[r]);
        }
        float *tmp = z_in;
        z_in = z_out;
        z_out = tmp;
    }
    /* clip to the unit disc: a / max(|a|, 1) */
    const float norm = sqrtf(z_in[0] * z_in[0] + z_in[1] * z_in[1]);
    const float inv = (norm > 1.0f) ? 1.0f / norm : 1.0f;
    action[0] = z_in[0] * inv;
    action[1] = z_in[1] * inv;
}

covey_status_t covey_action(const float *seq, int32_t n_steps, const float *goal_feat,
                            covey_scratch_t *scratch, float action[2])
{
    if (goal_feat == NULL || scratch == NULL || action == NULL || (seq == NULL && n_steps > 0)) {
        return COVEY_ERR_NULL;
    }
    action[0] = 0.0f;
    action[1] = 0.0f;
    if (n_steps < 0 || n_steps > COVEY_MAX_NEIGHBOURS) {
        return COVEY_ERR_RANGE;
    }
    covey_status_t worst = COVEY_OK;
    for (int32_t k = 0; k < n_steps * COVEY_INPUT + COVEY_GOAL; ++k) {
        float v = (k < n_steps * COVEY_INPUT) ? seq[k] : goal_feat[k - n_steps * COVEY_INPUT];
        covey_status_t st = check_abs(v, COVEY_MAX_ABS_FEATURE);
        if (st == COVEY_ERR_NONFINITE) {
            return st;
        }
        if (st != COVEY_OK) {
            worst = st;
        }
    }
    if (worst != COVEY_OK) {
        return worst;
    }
    run_network(seq, n_steps, goal_feat, scratch, action);
    return COVEY_OK;
}

/* ---- full guidance step ------------------------------------------------------- */

static covey_status_t fail(covey_command_t *out, covey_status_t status)
{
    if (out != NULL) {
        out->vel_n_m_s = 0.0f;
        out->vel_e_m_s = 0.0f;
        out->action[0] = 0.0f;
        out->action[1] = 0.0f;
    }
    return status;
}

covey_status_t covey_command(const covey_config_t *cfg, const covey_vehicle_t *own,
                             const covey_goal_t *goal, const covey_vehicle_t *nbrs,
                             int32_t n_nbrs, uint64_t now_us, covey_scratch_t *scratch,
                             covey_command_t *out)
{
    if (out != NULL) {
        out->n_used = 0;
        out->n_stale = 0;
        out->n_far = 0;
        out->n_excess = 0;
    }
    if (cfg == NULL || own == NULL || goal == NULL || scratch == NULL || out == NULL ||
        (nbrs == NULL && n_nbrs > 0)) {
        return fail(out, COVEY_ERR_NULL);
    }
    covey_status_t st = covey_config_check(cfg);
    if (st != COVEY_OK) {
        return fail(out, st);
    }
    if (n_nbrs < 0 || n_nbrs > COVEY_MAX_INPUTS) {
        return fail(out, COVEY_ERR_RANGE);
    }

    /* own state: fields, then freshness (age = now - stamp; a future stamp is a caller bug) */
    st = check_vehicle_fields(own);
    if (st != COVEY_OK) {
        return fail(out, st);
    }
    if (own->stamp_us > now_us) {
        return fail(out, COVEY_ERR_RANGE);
    }
    if (now_us - own->stamp_us > cfg->max_own_age_us) {
        return fail(out, COVEY_ERR_STALE);
    }
    if (!isfinite(goal->pos_n_m) || !isfinite(goal->pos_e_m)) {
        return fail(out, COVEY_ERR_NONFINITE);
    }
    st = check_abs(goal->pos_n_m, COVEY_MAX_ABS_POS_M);
    if (st == COVEY_OK) {
        st = check_abs(goal->pos_e_m, COVEY_MAX_ABS_POS_M);
    }
    if (st != COVEY_OK) {
        return fail(out, st);
    }

    /* metres -> policy units: 3 policy units of distance = separation_m */
    const float k_per_m = 3.0f / cfg->separation_m;

    /* candidates: fresh, valid, within the sense range */
    int32_t n_cand = 0;
    for (int32_t i = 0; i < n_nbrs; ++i) {
        const covey_vehicle_t *nb = &nbrs[i];
        if (nb->stamp_us > now_us) {
            return fail(out, COVEY_ERR_RANGE);
        }
        if (now_us - nb->stamp_us > cfg->max_neighbour_age_us) {
            out->n_stale++;
            continue;
        }
        st = check_vehicle_fields(nb);
        if (st != COVEY_OK) {
            return fail(out, st);
        }
        float r_n = nb->pos_n_m - own->pos_n_m;
        float r_e = nb->pos_e_m - own->pos_e_m;
        float d = k_per_m * sqrtf(r_n * r_n + r_e * r_e); /* sense range is before dist_scale */
        if (COVEY_W_SENSE_RANGE > 0.0f && d > COVEY_W_SENSE_RANGE) {
            out->n_far++;
            continue;
        }
        scratch->dist[i] = d;
        scratch->order[n_cand++] = (int16_t)i;
    }

    /* keep the nearest max_neighbours (ties: lower index), back in index order */
    if (n_cand > cfg->max_neighbours) {
        sort_by_dist_asc(scratch->order, n_cand, scratch->dist);
        out->n_excess = n_cand - cfg->max_neighbours;
        n_cand = cfg->max_neighbours;
        sort_by_index(scratch->order, n_cand);
    }
    if (COVEY_W_ORDER_CLOSEST_LAST) {
        /* decreasing distance, so the nearest neighbour is the last LSTM step */
        sort_by_dist_desc(scratch->order, n_cand, scratch->dist);
    }

    for (int32_t k = 0; k < n_cand; ++k) {
        encode_neighbour(own, &nbrs[scratch->order[k]], k_per_m, scratch->seq[k]);
    }
    encode_goal(own, goal, scratch->goal);
    run_network(&scratch->seq[0][0], n_cand, scratch->goal, scratch, out->action);

    /* body (fwd, right) -> NED: v_n = a_f cos h - a_r sin h, v_e = a_f sin h + a_r cos h */
    float c_h = cosf(own->heading_rad);
    float s_h = sinf(own->heading_rad);
    out->vel_n_m_s = cfg->cruise_speed_m_s * (out->action[0] * c_h - out->action[1] * s_h);
    out->vel_e_m_s = cfg->cruise_speed_m_s * (out->action[0] * s_h + out->action[1] * c_h);
    out->n_used = n_cand;
    return COVEY_OK;
}

uint32_t covey_scratch_bytes(void)
{
    return (uint32_t)sizeof(covey_scratch_t);
}

const char *covey_status_name(covey_status_t status)
{
    switch (status) {
    case COVEY_OK:
        return "ok";
    case COVEY_ERR_NULL:
        return "null";
    case COVEY_ERR_NONFINITE:
        return "nonfinite";
    case COVEY_ERR_RANGE:
        return "range";
    case COVEY_ERR_STALE:
        return "stale";
    }
    return "unknown";
}
