/* recursive.c: onboard/recursive.py in float32, with onboard.fixedpoint.update's front end (see recursive.h).
 *
 * Operation order (onboard/linalg32.py, docs/port-kit.md "The order"): every float32 sum starts from its first
 * term and adds the others in index order, every product and sum rounded on its own (-ffp-contract=off), as the
 * reference model does; keep it, and the results are the model's bits. */
#include "recursive.h"

#include <math.h>
#include <string.h>

/* ------------------------------------------------------------------------------------------ configuration */

size_t recursive_state_size(void)
{
    return sizeof(recursive_state_t);
}

void recursive_default_config(recursive_config_t *config)
{
    int i;
    memset(config, 0, sizeof *config);
    config->max_stars = 32;
    config->centroid_noise_px = 0.05;
    config->has_prior_sigma = 0;
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        config->prior_sigma[i] = 0.0;
        config->process_noise[i] = 0.0;
    }
    config->pair_gate_sigma = 5.0;
    config->max_iterations = 4;
    config->iteration_tol = 1e-2;
    config->reopen_after_frames = 5;
    config->burn_in_frames = 300;
    config->burn_in_power = 2.0;
    config->drift_detect = 1;
    config->drift_window_frames = 200;
    config->drift_start_frames = 400;
    config->drift_threshold = 4.5;
    config->drift_focal_mm_per_frame = 7e-5;
}

void recursive_default_prior_sigma(const recursive_camera_t *nominal, double distortion_px,
                                   double sigma[RECURSIVE_N_PARAMS])
{
    const double w = (double)nominal->image_size_px[0], h = (double)nominal->image_size_px[1];
    const double r = 0.5 * hypot(w, h);
    const double side = w > h ? w : h;
    const double r2 = r * r, r3 = r2 * r, r5 = r3 * r2, r7 = r5 * r2;
    sigma[0] = 0.03 * nominal->focal_length_mm;
    sigma[1] = 0.05 * side;
    sigma[2] = 0.05 * side;
    sigma[3] = distortion_px / r3;
    sigma[4] = distortion_px / r5;
    sigma[5] = distortion_px / r7;
    sigma[6] = distortion_px / r2;
    sigma[7] = distortion_px / r2;
    sigma[8] = distortion_px / r2;
    sigma[9] = distortion_px / r2;
}

int64_t recursive_update_cost_flops(int32_t n_stars, int32_t n_states, const recursive_config_t *config)
{
    int64_t n = n_stars < 0 ? 0 : n_stars, p, k, per;
    if (n > config->max_stars) {
        n = config->max_stars;
    }
    if (n < 3) {
        return 0;
    }
    p = 2 * n - 3;
    k = n_states;
    per = p * p * p / 3 + p * p * (k + 1) + 6 * p * k * k + 40 * n * k;
    return (int64_t)(config->max_iterations + 2) * per;
}

/* f in mm -> F in px for a sigma-like vector (onboard.recursive._to_model_units). */
static double to_model_units(double value, int slot, double pitch_um)
{
    return slot == 0 ? value * 1000.0 / pitch_um : value;
}

recursive_status_t recursive_create(recursive_state_t *state, const recursive_camera_t *nominal,
                                    uint32_t estimated_mask, const recursive_config_t *config)
{
    double sigma[RECURSIVE_N_PARAMS], theta64[RECURSIVE_N_PARAMS], scale;
    int32_t k = 0, i, j;
    if ((estimated_mask & 0x3ffu) == 0u || (estimated_mask & ~0x3ffu) != 0u) {
        return RECURSIVE_ERR_CONFIG;
    }
    if (config->max_stars < 3 || config->max_stars > RECURSIVE_MAX_STARS) {
        return RECURSIVE_ERR_CONFIG;
    }
    if (config->drift_window_frames > RECURSIVE_MAX_DRIFT_WINDOW || !(nominal->pixel_pitch_um > 0.0)) {
        return RECURSIVE_ERR_CONFIG;
    }
    if (config->has_prior_sigma) {
        for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
            sigma[i] = config->prior_sigma[i];
        }
    } else {
        recursive_default_prior_sigma(nominal, 5.0, sigma);
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        const double pn = config->process_noise[i];
        if (!isfinite(sigma[i]) || ((estimated_mask >> i) & 1u && !(sigma[i] > 0.0))) {
            return RECURSIVE_ERR_CONFIG;
        }
        if (!isfinite(pn) || pn < 0.0) {
            return RECURSIVE_ERR_CONFIG;
        }
    }
    memset(state, 0, sizeof *state);
    state->nominal = *nominal;
    state->config = *config;
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        if ((estimated_mask >> i) & 1u) {
            state->idx[k++] = i;
        }
    }
    state->k = k;
    theta64[0] = 1000.0 * nominal->focal_length_mm / nominal->pixel_pitch_um; /* F = 1000 f / p */
    theta64[1] = nominal->principal_point_px[0];
    theta64[2] = nominal->principal_point_px[1];
    for (i = 0; i < 7; ++i) {
        theta64[3 + i] = nominal->distortion[i];
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        state->theta_nom[i] = (float)theta64[i];
        scale = to_model_units(sigma[i], i, nominal->pixel_pitch_um);
        state->scale[i] = (float)(scale <= 0.0 ? 1.0 : scale);
    }
    for (j = 0; j < k; ++j) {
        const int32_t slot = state->idx[j];
        double s = to_model_units(sigma[slot], (int)slot, nominal->pixel_pitch_um);
        double ratio;
        if (s <= 0.0) {
            s = 1.0;
        }
        ratio = to_model_units(config->process_noise[slot], (int)slot, nominal->pixel_pitch_um) / s;
        state->q[j] = (float)(ratio * ratio);
        state->d[j] = 1.0f;
        state->d_prior[j] = 1.0f;
        state->u[j * k + j] = 1.0f;
    }
    {
        double s0 = to_model_units(sigma[0], 0, nominal->pixel_pitch_um);
        const double q = config->drift_focal_mm_per_frame * 1000.0 / nominal->pixel_pitch_um / (s0 <= 0.0 ? 1.0 : s0);
        state->q_drift = q * q;
    }
    state->window = config->drift_window_frames > 1 ? config->drift_window_frames : 1;
    state->drift_frame = -1;
    return RECURSIVE_OK;
}

/* ----------------------------------------------------------------------------- the model at the current state */

/* s = fl(a + b) and its exact rounding error (Knuth's TwoSum). */
static void two_sum(float a, float b, float *s, float *err)
{
    const float sum = a + b;
    const float bb = sum - a;
    *err = (a - (sum - bb)) + (b - bb);
    *s = sum;
}

/* Fill work.theta_r = fl(theta_nom + s x_hi) and return (in delta) the rounding left out, in state units. */
static void linearisation_point(recursive_state_t *st, const float *x_hi, const float *x_lo, float *delta)
{
    float step[RECURSIVE_N_PARAMS], err[RECURSIVE_N_PARAMS];
    int32_t i;
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        step[i] = 0.0f;
    }
    for (i = 0; i < st->k; ++i) {
        step[st->idx[i]] = st->scale[st->idx[i]] * x_hi[i];
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        two_sum(st->theta_nom[i], step[i], &st->work.theta_r[i], &err[i]);
    }
    for (i = 0; i < st->k; ++i) {
        delta[i] = err[st->idx[i]] / st->scale[st->idx[i]] + x_lo[i];
    }
}

/* h_row . x over the k state columns, summed in order (the rows of onboard.linalg32.matvec). */
static float row_dot(const float *h_row, const float *x, size_t k)
{
    float acc = h_row[0] * x[0];
    size_t col;
    for (col = 1u; col < k; ++col) {
        acc += h_row[col] * x[col];
    }
    return acc;
}

/* The ordered stars' centroids and reference vectors (xs_all[order], ys_all[order], rs_all[order]). */
static void ordered_stars(const recursive_work_t *w, const int32_t *order, size_t n, float *xs, float *ys,
                          float (*rs)[3])
{
    size_t i, c;
    for (i = 0u; i < n; ++i) {
        xs[i] = w->xs[order[i]];
        ys[i] = w->ys[order[i]];
        for (c = 0u; c < 3u; ++c) {
            rs[i][c] = w->rs[order[i]][c];
        }
    }
}

/* jb = d b / d state: the estimated columns of d b / d theta times the state scale (jb_theta[:, :, idx] * scale). */
static void state_jacobians(recursive_state_t *st, size_t n)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k;
    size_t i, c, col;
    for (i = 0u; i < n; ++i) {
        for (c = 0u; c < 3u; ++c) {
            for (col = 0u; col < k; ++col) {
                const int32_t slot = st->idx[col];
                w->jb[(i * 3u + c) * k + col] = w->jb_theta[i][c][slot] * st->scale[slot];
            }
        }
    }
}

/* The fixed-point front end's residuals (the `front` of onboard.recursive._linearise): evaluated at theta_r on its
 * grids (theta_q), whose rounding joins delta. */
static recursive_status_t front_end_residuals(recursive_state_t *st, const int32_t *order, size_t n, float *delta)
{
    recursive_work_t *w = &st->work;
    recursive_linearised_t *lin = &w->lin;
    fixedpoint_camera_t cam;
    int64_t b_q30[RECURSIVE_MAX_STARS][3], r_q30[RECURSIVE_MAX_STARS][3], e_q61[RECURSIVE_MAX_PAIRS];
    size_t i, c, col;
    if (fixedpoint_camera(w->theta_r, st->nominal.image_size_px[0], st->nominal.image_size_px[1], &cam) !=
        FIXEDPOINT_OK) {
        return RECURSIVE_ERR_FIXED_RANGE;
    }
    for (i = 0u; i < n; ++i) {
        if (fixedpoint_pixels_to_unit_q30(w->x_q10[order[i]], w->y_q10[order[i]], &cam, b_q30[i]) != FIXEDPOINT_OK) {
            return RECURSIVE_ERR_FIXED_RANGE;
        }
        for (c = 0u; c < 3u; ++c) {
            r_q30[i][c] = w->r_q30[order[i]][c];
        }
    }
    fixedpoint_difference_residuals_q61((const int64_t (*)[3])b_q30, (const int64_t (*)[3])r_q30, lin->pi, lin->pj,
                                        lin->n_pairs, e_q61);
    fixedpoint_residuals_to_float(e_q61, lin->n_pairs, lin->e);
    for (col = 0u; col < (size_t)st->k; ++col) {
        const int32_t slot = st->idx[col];
        const double rounding = ((double)w->theta_r[slot] - cam.theta_q[slot]) / (double)st->scale[slot];
        delta[col] = delta[col] + (float)rounding;
    }
    return RECURSIVE_OK;
}

/* R jittered and divided by its mean diagonal r_norm (summed in order). A star nearly on the line through the base
 * pair makes R nearly singular: the jitter bounds its condition (onboard.recursive._R_JITTER). */
static void normalise_pair_covariance(recursive_linearised_t *lin)
{
    const size_t m = lin->n_pairs;
    float sum = lin->r[0], r_norm32;
    double mean_diag;
    size_t p, q;
    for (p = 1u; p < m; ++p) {
        sum += lin->r[p * m + p];
    }
    mean_diag = (double)(sum / (float)m);
    lin->r_norm = mean_diag > 0.0 ? mean_diag : 1.0;
    for (p = 0u; p < m; ++p) {
        lin->r[p * m + p] *= (float)(1.0 + RECURSIVE_R_JITTER);
    }
    r_norm32 = (float)lin->r_norm;
    for (p = 0u; p < m; ++p) {
        for (q = 0u; q < m; ++q) {
            lin->r[p * m + q] /= r_norm32;
        }
    }
}

/* Residuals, Jacobian (state units) and pair covariance of the n ordered stars order[] (indices of the selected
 * stars), at the state x_hi + x_lo (onboard.recursive._linearise). */
static recursive_status_t linearise(recursive_state_t *st, const int32_t *order, size_t n, const float *x_hi,
                                    const float *x_lo)
{
    recursive_work_t *w = &st->work;
    recursive_linearised_t *lin = &w->lin;
    const size_t k = (size_t)st->k;
    float xs[RECURSIVE_MAX_STARS] = {0.0f}, ys[RECURSIVE_MAX_STARS] = {0.0f}, rs[RECURSIVE_MAX_STARS][3] = {{0.0f}};
    float delta[RECURSIVE_MAX_STATES];
    size_t p;
    linearisation_point(st, x_hi, x_lo, delta);
    ordered_stars(w, order, n, xs, ys, rs);
    camera_unit_vector_jacobians(xs, ys, n, w->theta_r, w->b, w->jb_theta, w->jb_centroid);
    state_jacobians(st, n);
    lin->n_pairs = interstar_independent_pairs(n, lin->pi, lin->pj);
    if (!w->fixed) {
        interstar_difference_residuals((const float (*)[3])w->b, (const float (*)[3])rs, lin->pi, lin->pj,
                                       lin->n_pairs, lin->e);
    } else {
        const recursive_status_t status = front_end_residuals(st, order, n, delta);
        if (status != RECURSIVE_OK) {
            return status;
        }
    }
    interstar_difference_jacobian((const float (*)[3])w->b, w->jb, k, lin->pi, lin->pj, lin->n_pairs, lin->h);
    for (p = 0u; p < lin->n_pairs; ++p) { /* e - H delta */
        lin->e[p] = lin->e[p] - row_dot(&lin->h[p * k], delta, k);
    }
    interstar_pair_covariance((const float (*)[3])w->b, (const float (*)[3][2])w->jb_centroid, lin->pi, lin->pj,
                              lin->n_pairs, st->config.centroid_noise_px, lin->r);
    normalise_pair_covariance(lin);
    return RECURSIVE_OK;
}

/* e_p^2 / (h_p P h_p + R_pp) of every pair, P = U D U^T of the state. */
static void pair_chi2(const recursive_state_t *st, float *chi2)
{
    const recursive_linearised_t *lin = &st->work.lin;
    const size_t k = (size_t)st->k;
    const float r_norm32 = (float)lin->r_norm;
    size_t p, i, j;
    for (p = 0u; p < lin->n_pairs; ++p) {
        float s = 0.0f;
        for (j = 0u; j < k; ++j) {
            float g = lin->h[p * k] * st->u[j];
            for (i = 1u; i < k; ++i) {
                g += lin->h[p * k + i] * st->u[i * k + j];
            }
            s = j == 0u ? g * g * st->d[0] : s + g * g * st->d[j];
        }
        s = s + lin->r[p * lin->n_pairs + p] * r_norm32;
        chi2[p] = lin->e[p] * lin->e[p] / s;
    }
}

/* Misidentified stars from the failing independent pairs (order (0,1), (0,k)..., (1,k)...). */
static void misidentified(const uint8_t *fail, size_t n, uint8_t *bad)
{
    size_t i, n0 = 0u, n1 = 0u;
    for (i = 0u; i < n; ++i) {
        bad[i] = 0u;
    }
    for (i = 2u; i < n; ++i) {
        bad[i] = (uint8_t)(fail[i - 1u] && fail[n - 1u + i - 2u]);
        n0 += fail[i - 1u];
        n1 += fail[n - 1u + i - 2u];
    }
    if (fail[0] && n > 2u) {
        bad[0] = (uint8_t)((double)n0 / (double)(n - 2u) > 0.5);
        bad[1] = (uint8_t)((double)n1 / (double)(n - 2u) > 0.5);
    }
}

/* ------------------------------------------------------------------------------------------ per-frame step */

static void time_update(recursive_state_t *st)
{
    const int64_t frame = st->frames;
    const recursive_config_t *cfg = &st->config;
    const size_t k = (size_t)st->k;
    float a[RECURSIVE_MAX_STATES];
    size_t j, l;
    if (2 <= frame && frame <= cfg->burn_in_frames && cfg->burn_in_power > 0.0) {
        const float grow = (float)pow((double)frame / (double)(frame - 1), cfg->burn_in_power);
        for (j = 0u; j < k; ++j) {
            st->d[j] *= grow;
        }
    }
    for (j = 0u; j < k; ++j) {
        double q = (double)st->q[j];
        if (j == 0u && st->drift_on && st->idx[0] == 0) {
            q += st->q_drift;
        }
        if (q == 0.0) {
            continue;
        }
        for (l = 0u; l < k; ++l) {
            a[l] = 0.0f;
        }
        a[j] = 1.0f;
        ud_agee_turner_update(st->u, st->d, a, (float)q, k);
    }
}

/* Focal-length score of a frame at the prior and its predicted variance (onboard.recursive._focal_score). */
static void focal_score(const recursive_state_t *st, size_t rows, double *g, double *var)
{
    const float *white = st->work.white;
    const size_t k = (size_t)st->k, cols = k + 1u;
    float a[RECURSIVE_MAX_STATES], t[RECURSIVE_MAX_STATES], dot, hh, ad;
    size_t p, i, j;
    if (st->idx[0] != 0) {
        *g = 0.0;
        *var = 0.0;
        return;
    }
    dot = white[1] * white[0];
    hh = white[1] * white[1];
    for (p = 1u; p < rows; ++p) {
        dot += white[p * cols + 1u] * white[p * cols];
        hh += white[p * cols + 1u] * white[p * cols + 1u];
    }
    for (i = 0u; i < k; ++i) { /* t = H^T h_f */
        t[i] = white[1u + i] * white[1];
        for (p = 1u; p < rows; ++p) {
            t[i] += white[p * cols + 1u + i] * white[p * cols + 1u];
        }
    }
    ad = 0.0f;
    for (j = 0u; j < k; ++j) { /* a = U^T t */
        a[j] = st->u[j] * t[0];
        for (i = 1u; i < k; ++i) {
            a[j] += st->u[i * k + j] * t[i];
        }
        ad = j == 0u ? a[0] * a[0] * st->d[0] : ad + a[j] * a[j] * st->d[j];
    }
    *g = (double)dot;
    *var = (double)(hh + ad);
}

static void record_history(recursive_state_t *st, const recursive_frame_result_t *result)
{
    st->ring_g[st->ring_pos] = result != NULL ? (float)result->focal_score : 0.0f;
    st->ring_v[st->ring_pos] = result != NULL ? (float)result->focal_score_var : 0.0f;
    st->ring_pos = (st->ring_pos + 1) % st->window;
    st->ring_count = st->ring_count + 1 < st->window ? st->ring_count + 1 : st->window;
}

double recursive_drift_statistic(const recursive_state_t *st)
{
    float sum_g, sum_v;
    double lam = 1.0, var;
    int32_t i;
    if (st->idx[0] != 0 || st->ring_count < st->window) {
        return NAN;
    }
    sum_g = st->ring_g[0];
    sum_v = st->ring_v[0];
    for (i = 1; i < st->window; ++i) {
        sum_g += st->ring_g[i];
        sum_v += st->ring_v[i];
    }
    var = (double)sum_v;
    if (st->nis_count > 0) {
        lam = st->nis_sum / (double)st->nis_count;
        lam = lam > 1.0 ? lam : 1.0;
    }
    if (!(var > 0.0)) {
        return NAN;
    }
    return (double)sum_g / sqrt(lam * var);
}

static void detect_drift(recursive_state_t *st)
{
    const recursive_config_t *cfg = &st->config;
    double z;
    if (!cfg->drift_detect || st->drift_on || st->idx[0] != 0 || st->frames <= cfg->drift_start_frames) {
        return;
    }
    z = recursive_drift_statistic(st);
    if (isfinite(z) && fabs(z) > cfg->drift_threshold) {
        st->drift_on = 1;
        st->drift_frame = st->frames;
    }
}

/* How many of the n flags are set. */
static size_t count_set(const uint8_t *flags, size_t n)
{
    size_t i, count = 0u;
    for (i = 0u; i < n; ++i) {
        count += flags[i];
    }
    return count;
}

/* The selected stars still kept, in pair order (live[order_for_pairs(xs[live], ys[live])]); returns how many. */
static size_t ordered_live_stars(const recursive_work_t *w, const uint8_t *keep, int32_t *order)
{
    float xl[RECURSIVE_MAX_STARS], yl[RECURSIVE_MAX_STARS];
    int32_t live[RECURSIVE_MAX_STARS], perm[RECURSIVE_MAX_STARS];
    size_t n_live = 0u, i;
    for (i = 0u; i < (size_t)w->n_sel; ++i) {
        if (keep[i]) {
            live[n_live++] = (int32_t)i;
        }
    }
    if (n_live < 3u) {
        return n_live;
    }
    for (i = 0u; i < n_live; ++i) {
        xl[i] = w->xs[live[i]];
        yl[i] = w->ys[live[i]];
    }
    interstar_order_for_pairs(xl, yl, n_live, perm);
    for (i = 0u; i < n_live; ++i) {
        order[i] = live[perm[i]];
    }
    return n_live;
}

/* Gate at the prior, removing misidentified stars from keep (at most two passes); leaves the order in order[]
 * (n_order stars), the linearisation in work.lin and the failing pairs in fail[] (onboard.recursive._gate). */
static recursive_status_t gate(recursive_state_t *st, uint8_t *keep, int32_t *order, size_t *n_order, uint8_t *fail,
                               recursive_skip_t *skip)
{
    recursive_work_t *w = &st->work;
    const float gate2_32 = (float)(st->config.pair_gate_sigma * st->config.pair_gate_sigma);
    float chi2[RECURSIVE_MAX_PAIRS];
    uint8_t bad[RECURSIVE_MAX_STARS];
    size_t n_live, i, p, n_bad;
    int pass;
    recursive_status_t status;
    *skip = RECURSIVE_SKIP_NONE;
    for (pass = 0; pass < 3; ++pass) {
        n_live = ordered_live_stars(w, keep, order);
        if (n_live < 3u) {
            *skip = RECURSIVE_SKIP_FEW_CONSISTENT;
            return RECURSIVE_OK;
        }
        *n_order = n_live;
        status = linearise(st, order, n_live, st->x_hi, st->x_lo);
        if (status != RECURSIVE_OK) {
            return status;
        }
        pair_chi2(st, chi2);
        for (p = 0u; p < w->lin.n_pairs; ++p) {
            fail[p] = (uint8_t)(chi2[p] > gate2_32);
        }
        misidentified(fail, n_live, bad);
        n_bad = count_set(bad, n_live);
        if (n_bad == 0u || pass == 2 || n_bad > n_live / 2u) {
            break;
        }
        for (i = 0u; i < n_live; ++i) {
            if (bad[i]) {
                keep[order[i]] = 0u;
            }
        }
    }
    if ((double)count_set(fail, w->lin.n_pairs) / (double)w->lin.n_pairs > 0.5) {
        *skip = RECURSIVE_SKIP_MOST_INCONSISTENT;
    }
    return RECURSIVE_OK;
}

/* Lower Cholesky factor of the m x m matrix a (row-major) into l; 0 when a is not positive definite. */
static int cholesky(const float *a, size_t m, float *l)
{
    size_t i, j, c;
    for (i = 0u; i < m * m; ++i) {
        l[i] = 0.0f;
    }
    for (j = 0u; j < m; ++j) {
        float diag = a[j * m + j];
        for (c = 0u; c < j; ++c) {
            diag -= l[j * m + c] * l[j * m + c];
        }
        if (!(diag > 0.0f)) {
            return 0;
        }
        l[j * m + j] = sqrtf(diag);
        for (i = j + 1u; i < m; ++i) {
            float v = a[i * m + j];
            for (c = 0u; c < j; ++c) {
                v -= l[i * m + c] * l[j * m + c];
            }
            l[i * m + j] = v / l[j * m + j];
        }
    }
    return 1;
}

/* The pseudo-measurement of xi = x - x_prior over the used pairs, y = e(x_lin) + H dx with dx = x_lin - x_prior,
 * whitened: work.white = L^-1 [y s, H s], R_used = L L^T, s = 1 / sqrt(r_norm) (onboard.recursive._whiten). */
static recursive_status_t whiten(recursive_state_t *st, const int32_t *used_idx, size_t n_used, const float *dx)
{
    recursive_work_t *w = &st->work;
    const recursive_linearised_t *lin = &w->lin;
    const size_t k = (size_t)st->k, cols = k + 1u;
    float y[RECURSIVE_MAX_PAIRS], scale;
    size_t p, q, j;
    for (p = 0u; p < n_used; ++p) {
        const size_t row = (size_t)used_idx[p];
        y[p] = lin->e[row] + row_dot(&lin->h[row * k], dx, k);
        for (q = 0u; q < n_used; ++q) {
            w->r_used[p * n_used + q] = lin->r[row * lin->n_pairs + (size_t)used_idx[q]];
        }
    }
    if (!cholesky(w->r_used, n_used, w->chol)) {
        return RECURSIVE_ERR_NOT_POSITIVE;
    }
    scale = (float)(1.0 / sqrt(lin->r_norm));
    for (p = 0u; p < n_used; ++p) { /* forward substitution */
        const size_t row = (size_t)used_idx[p];
        for (j = 0u; j < cols; ++j) {
            float v = j == 0u ? y[p] * scale : lin->h[row * k + j - 1u] * scale;
            for (q = 0u; q < p; ++q) {
                v -= w->chol[p * n_used + q] * w->white[q * cols + j];
            }
            w->white[p * cols + j] = v / w->chol[p * n_used + p];
        }
    }
    return RECURSIVE_OK;
}

/* The whitened rows into the U-D factors by Bierman's update, xi from zero; returns the summed squared normalised
 * innovations (onboard.recursive._bierman_pass). */
static double bierman_pass(recursive_state_t *st, size_t n_rows)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k, cols = k + 1u;
    double nis = 0.0;
    size_t j, p;
    for (j = 0u; j < k; ++j) {
        w->xi[j] = 0.0f;
    }
    for (p = 0u; p < n_rows; ++p) {
        float s;
        const float innov = ud_bierman_update(st->u, st->d, w->xi, &w->white[p * cols + 1u], w->white[p * cols], k, &s);
        nis += (double)(innov * innov / s);
    }
    return nis;
}

/* The new estimate prior + xi, compensated (TwoSum), into lin_hi + lin_lo; its change from the last linearisation
 * point into step_state; returns the largest |change|. */
static float take_step(const recursive_state_t *st, const float *prior_hi, const float *prior_lo, float *lin_hi,
                       float *lin_lo, float *step_state)
{
    float step = 0.0f;
    size_t j;
    for (j = 0u; j < (size_t)st->k; ++j) {
        float new_hi, new_lo;
        two_sum(prior_hi[j], st->work.xi[j] + prior_lo[j], &new_hi, &new_lo);
        step_state[j] = (new_hi - lin_hi[j]) + (new_lo - lin_lo[j]);
        if (fabsf(step_state[j]) > step) {
            step = fabsf(step_state[j]);
        }
        lin_hi[j] = new_hi;
        lin_lo[j] = new_lo;
    }
    return step;
}

/* The iterated update of the gated frame (the n_used pairs used_idx[] of the n_order stars order[]): relinearise
 * from the prior's factors, whiten, Bierman, step, until the step is within iteration_tol or max_iterations. Leaves
 * the estimate in x_hi + x_lo and the last step in step_state (onboard.recursive._iterated_update). */
static recursive_status_t iterated_update(recursive_state_t *st, const int32_t *order, size_t n_order,
                                          const int32_t *used_idx, size_t n_used, const float *prior_hi,
                                          const float *prior_lo, recursive_frame_result_t *result, float *step_state)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k;
    const size_t max_it = st->config.max_iterations > 1 ? (size_t)st->config.max_iterations : 1u;
    float lin_hi[RECURSIVE_MAX_STATES], lin_lo[RECURSIVE_MAX_STATES], dx[RECURSIVE_MAX_STATES];
    double nis = 0.0, score = 0.0, score_var = 0.0;
    size_t j, it;
    recursive_status_t status;
    for (j = 0u; j < k; ++j) {
        lin_hi[j] = prior_hi[j];
        lin_lo[j] = prior_lo[j];
        step_state[j] = 0.0f;
    }
    for (it = 0u; it < max_it; ++it) {
        if (it > 0u) {
            memcpy(st->u, w->u0, sizeof(float) * k * k);
            memcpy(st->d, w->d0, sizeof(float) * k);
            status = linearise(st, order, n_order, lin_hi, lin_lo);
            if (status != RECURSIVE_OK) {
                return status;
            }
        }
        for (j = 0u; j < k; ++j) {
            dx[j] = (lin_hi[j] - prior_hi[j]) + (lin_lo[j] - prior_lo[j]);
        }
        status = whiten(st, used_idx, n_used, dx);
        if (status != RECURSIVE_OK) {
            return status;
        }
        if (it == 0u) {
            focal_score(st, n_used, &score, &score_var);
        }
        nis = bierman_pass(st, n_used);
        result->iterations = (int32_t)(it + 1u);
        if ((double)take_step(st, prior_hi, prior_lo, lin_hi, lin_lo, step_state) <= st->config.iteration_tol) {
            break;
        }
    }
    for (j = 0u; j < k; ++j) {
        st->x_hi[j] = lin_hi[j];
        st->x_lo[j] = lin_lo[j];
    }
    result->nis = nis / (double)(n_used > 1u ? n_used : 1u);
    result->focal_score = score;
    result->focal_score_var = score_var;
    return RECURSIVE_OK;
}

/* Post-fit editing: every pair's residual at the updated state (the linear prediction e - H step from the last
 * point) gated again; flags in post_bad the misidentified stars when they are at most half the frame
 * (onboard.recursive._post_fit_bad). */
static void post_fit_bad(const recursive_state_t *st, const int32_t *order, size_t n_order, const float *step_state,
                         uint8_t *post_bad)
{
    const recursive_linearised_t *lin = &st->work.lin;
    const size_t k = (size_t)st->k;
    const float gate2_32 = (float)(st->config.pair_gate_sigma * st->config.pair_gate_sigma);
    const float r_norm32 = (float)lin->r_norm;
    uint8_t fail_post[RECURSIVE_MAX_PAIRS], bad[RECURSIVE_MAX_STARS];
    size_t p, i, n_bad;
    for (p = 0u; p < lin->n_pairs; ++p) {
        const float post = lin->e[p] - row_dot(&lin->h[p * k], step_state, k);
        fail_post[p] = (uint8_t)(post * post > gate2_32 * lin->r[p * lin->n_pairs + p] * r_norm32);
    }
    misidentified(fail_post, n_order, bad);
    n_bad = count_set(bad, n_order);
    if (n_bad > 0u && n_bad <= n_order / 2u) {
        for (i = 0u; i < n_order; ++i) {
            if (bad[i]) {
                post_bad[order[i]] = 1u;
            }
        }
    }
}

/* One attempt at a frame from the prior (work.u0, work.d0, prior_hi + prior_lo): gate, iterated update, post-fit
 * editing; flags in post_bad (over the selected stars) the stars the post-fit residuals reject
 * (onboard.recursive._process_frame). */
static recursive_status_t process_frame(recursive_state_t *st, uint8_t *keep, const float *prior_hi,
                                        const float *prior_lo, recursive_frame_result_t *result, uint8_t *post_bad,
                                        recursive_skip_t *skip)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k;
    int32_t order[RECURSIVE_MAX_STARS], used_idx[RECURSIVE_MAX_PAIRS];
    uint8_t fail[RECURSIVE_MAX_PAIRS];
    float step_state[RECURSIVE_MAX_STATES];
    size_t n_order = 0u, n_used = 0u, i, j, p;
    recursive_status_t status;
    for (i = 0u; i < (size_t)w->n_sel; ++i) {
        post_bad[i] = 0u;
    }
    for (j = 0u; j < k; ++j) {
        st->x_hi[j] = prior_hi[j];
        st->x_lo[j] = prior_lo[j];
    }
    status = gate(st, keep, order, &n_order, fail, skip);
    if (status != RECURSIVE_OK || *skip != RECURSIVE_SKIP_NONE) {
        return status;
    }
    for (p = 0u; p < w->lin.n_pairs; ++p) {
        if (!fail[p]) {
            used_idx[n_used++] = (int32_t)p;
        }
    }
    result->n_used = (int32_t)n_order;
    result->n_pairs = (int32_t)n_used;
    result->n_pairs_rejected = (int32_t)(w->lin.n_pairs - n_used);
    status = iterated_update(st, order, n_order, used_idx, n_used, prior_hi, prior_lo, result, step_state);
    if (status != RECURSIVE_OK) {
        return status;
    }
    post_fit_bad(st, order, n_order, step_state, post_bad);
    return RECURSIVE_OK;
}

/* Restore a factor pair to the identity and the prior's D (the covariance reopened). */
static void reopen_covariance(recursive_state_t *st)
{
    const size_t k = (size_t)st->k;
    size_t j;
    memset(st->u, 0, sizeof(float) * k * k);
    for (j = 0u; j < k; ++j) {
        st->u[j * k + j] = 1.0f;
        st->d[j] = st->d_prior[j];
    }
}

/* Frames from the prior with post-fit editing: a star the updated state still cannot explain is removed from keep
 * and the frame redone from the prior, once (onboard.recursive._process_with_editing). */
static recursive_status_t process_with_editing(recursive_state_t *st, uint8_t *keep, const float *prior_hi,
                                               const float *prior_lo, recursive_frame_result_t *result,
                                               recursive_skip_t *skip)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k, n_sel = (size_t)w->n_sel;
    uint8_t post_bad[RECURSIVE_MAX_STARS];
    size_t i;
    int attempt;
    for (attempt = 0; attempt < 2; ++attempt) {
        int any_bad = 0;
        recursive_status_t status;
        if (attempt) {
            memcpy(st->u, w->u0, sizeof(float) * k * k);
            memcpy(st->d, w->d0, sizeof(float) * k);
        }
        status = process_frame(st, keep, prior_hi, prior_lo, result, post_bad, skip);
        if (status != RECURSIVE_OK) {
            return status;
        }
        for (i = 0u; i < n_sel; ++i) {
            any_bad |= post_bad[i];
        }
        if (*skip != RECURSIVE_SKIP_NONE || !any_bad) {
            break;
        }
        for (i = 0u; i < n_sel; ++i) {
            if (post_bad[i]) {
                keep[i] = 0u;
            }
        }
    }
    return RECURSIVE_OK;
}

/* A skipped frame: the prior's factors back; a run of inconsistent frames reopens the covariance
 * (onboard.recursive._skip_frame). */
static void skip_frame(recursive_state_t *st, recursive_skip_t skip, recursive_frame_result_t *result)
{
    const size_t k = (size_t)st->k;
    memcpy(st->u, st->work.u0, sizeof(float) * k * k);
    memcpy(st->d, st->work.d0, sizeof(float) * k);
    result->skipped = (int32_t)skip;
    if (skip == RECURSIVE_SKIP_MOST_INCONSISTENT) {
        st->inconsistent_run += 1;
        if (st->inconsistent_run >= st->config.reopen_after_frames) {
            reopen_covariance(st);
            st->inconsistent_run = 0;
            result->reopened = 1;
        }
    }
    record_history(st, NULL);
}

/* An updated frame: the counters, the NIS of single-iteration frames and the drift detector
 * (onboard.recursive._accept_frame). */
static void accept_frame(recursive_state_t *st, const recursive_frame_result_t *result)
{
    st->inconsistent_run = 0;
    st->updates += 1;
    if (st->frames > st->config.drift_start_frames && result->iterations == 1) {
        st->nis_sum += result->nis * (double)result->n_pairs;
        st->nis_count += result->n_pairs;
    }
    record_history(st, result);
    detect_drift(st);
}

/* The frame once its stars are selected into work (xs, ys, rs and, fixed, the integers): onboard.recursive.update
 * from the time update on. */
static recursive_status_t update_selected(recursive_state_t *st, recursive_frame_result_t *result)
{
    recursive_work_t *w = &st->work;
    const size_t k = (size_t)st->k, n_sel = (size_t)w->n_sel;
    float prior_hi[RECURSIVE_MAX_STATES], prior_lo[RECURSIVE_MAX_STATES];
    uint8_t keep[RECURSIVE_MAX_STARS];
    recursive_skip_t skip = RECURSIVE_SKIP_NONE;
    recursive_status_t status;
    size_t i, j;
    st->frames += 1;
    time_update(st);
    if (n_sel < 3u) {
        result->skipped = RECURSIVE_SKIP_FEW_STARS;
        record_history(st, NULL);
        return RECURSIVE_OK;
    }
    for (i = 0u; i < n_sel; ++i) {
        keep[i] = 1u;
    }
    memcpy(w->u0, st->u, sizeof(float) * k * k);
    memcpy(w->d0, st->d, sizeof(float) * k);
    for (j = 0u; j < k; ++j) {
        prior_hi[j] = st->x_hi[j];
        prior_lo[j] = st->x_lo[j];
    }
    status = process_with_editing(st, keep, prior_hi, prior_lo, result, &skip);
    if (status != RECURSIVE_OK) {
        return status;
    }
    result->n_rejected_stars = 0;
    for (i = 0u; i < n_sel; ++i) {
        if (!keep[i]) {
            result->rejected_stars[result->n_rejected_stars++] = w->sel[i];
        }
    }
    if (skip != RECURSIVE_SKIP_NONE) {
        skip_frame(st, skip, result);
    } else {
        accept_frame(st, result);
    }
    return RECURSIVE_OK;
}

static void clear_result(recursive_frame_result_t *result, size_t n)
{
    memset(result, 0, sizeof *result);
    result->n_stars = (int32_t)n;
    result->nis = NAN;
}

/* Whether selected star (x, y) repeats an earlier selected star's centroid (onboard.recursive._distinct_stars). */
static int repeats(const recursive_work_t *w, float x, float y)
{
    int32_t i;
    for (i = 0; i < w->n_sel; ++i) {
        if (w->xs[i] == x && w->ys[i] == y) {
            return 1;
        }
    }
    return 0;
}

recursive_status_t recursive_update(recursive_state_t *state, const float *x_px, const float *y_px,
                                    const float (*r_ref)[3], const uint8_t *identified, size_t n,
                                    recursive_frame_result_t *result)
{
    recursive_work_t *w = &state->work;
    size_t i;
    int c;
    clear_result(result, n);
    w->fixed = 0;
    w->n_sel = 0;
    for (i = 0u; i < n && w->n_sel < state->config.max_stars; ++i) {
        if (!(isfinite(x_px[i]) && isfinite(y_px[i]) && isfinite(r_ref[i][0]) && isfinite(r_ref[i][1]) &&
              isfinite(r_ref[i][2])) ||
            (identified != NULL && !identified[i]) || repeats(w, x_px[i], y_px[i])) {
            continue;
        }
        w->sel[w->n_sel] = (int32_t)i;
        w->xs[w->n_sel] = x_px[i];
        w->ys[w->n_sel] = y_px[i];
        for (c = 0; c < 3; ++c) {
            w->rs[w->n_sel][c] = r_ref[i][c];
        }
        w->n_sel += 1;
    }
    return update_selected(state, result);
}

recursive_status_t recursive_update_fixed(recursive_state_t *state, const int64_t *x_q10, const int64_t *y_q10,
                                          const int64_t (*r_q30)[3], const uint8_t *identified, size_t n,
                                          recursive_frame_result_t *result)
{
    recursive_work_t *w = &state->work;
    const float step_px = 1.0f / (float)((int32_t)1 << FIXEDPOINT_CENTROID_FRAC_BITS);
    size_t i;
    int c;
    clear_result(result, n);
    w->fixed = 1;
    w->n_sel = 0;
    for (i = 0u; i < n && w->n_sel < state->config.max_stars; ++i) {
        float x, y;
        if ((identified != NULL && !identified[i]) ||
            !fixedpoint_on_detector(x_q10[i], y_q10[i], state->nominal.image_size_px[0],
                                    state->nominal.image_size_px[1])) {
            continue;
        }
        x = (float)x_q10[i] * step_px; /* exact: on the detector |x_q10| < 2^24 */
        y = (float)y_q10[i] * step_px;
        if (repeats(w, x, y)) {
            continue;
        }
        w->sel[w->n_sel] = (int32_t)i;
        w->xs[w->n_sel] = x;
        w->ys[w->n_sel] = y;
        w->x_q10[w->n_sel] = x_q10[i];
        w->y_q10[w->n_sel] = y_q10[i];
        for (c = 0; c < 3; ++c) {
            w->rs[w->n_sel][c] = 0.0f; /* unused: the front end's residuals replace the float ones */
            w->r_q30[w->n_sel][c] = r_q30[i][c];
        }
        w->n_sel += 1;
    }
    return update_selected(state, result);
}

/* ----------------------------------------------------------------------------------------- reading the state */

void recursive_state_vector(const recursive_state_t *state, double theta[RECURSIVE_N_PARAMS])
{
    int32_t i;
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        theta[i] = (double)state->theta_nom[i];
    }
    for (i = 0; i < state->k; ++i) {
        const int32_t slot = state->idx[i];
        theta[slot] += (double)state->scale[slot] * ((double)state->x_hi[i] + (double)state->x_lo[i]);
    }
}

void recursive_sigma(const recursive_state_t *state, double sigma[RECURSIVE_N_PARAMS])
{
    double p[RECURSIVE_MAX_STATES * RECURSIVE_MAX_STATES];
    const size_t k = (size_t)state->k;
    size_t i;
    for (i = 0u; i < RECURSIVE_N_PARAMS; ++i) {
        sigma[i] = NAN;
    }
    ud_covariance(state->u, state->d, k, p);
    for (i = 0u; i < k; ++i) {
        const int32_t slot = state->idx[i];
        const double s = (double)state->scale[slot];
        const double sd = sqrt(p[i * k + i] * (s * s));
        sigma[slot] = slot == 0 ? sd * state->nominal.pixel_pitch_um / 1000.0 : sd;
    }
}

/* ------------------------------------------------------------------------------------------- save / restore */

static void put_i64(uint8_t *out, int64_t value)
{
    uint64_t v = (uint64_t)value;
    int i;
    for (i = 0; i < 8; ++i) {
        out[i] = (uint8_t)(v & 0xffu);
        v >>= 8;
    }
}

static int64_t get_i64(const uint8_t *in)
{
    uint64_t v = 0u;
    int i;
    for (i = 7; i >= 0; --i) {
        v = (v << 8) | in[i];
    }
    return (int64_t)v; /* two's complement on every target this core supports */
}

static void put_f32(uint8_t *out, float value)
{
    uint32_t v;
    int i;
    memcpy(&v, &value, sizeof v);
    for (i = 0; i < 4; ++i) {
        out[i] = (uint8_t)(v & 0xffu);
        v >>= 8;
    }
}

static float get_f32(const uint8_t *in)
{
    uint32_t v = 0u;
    float value;
    int i;
    for (i = 3; i >= 0; --i) {
        v = (v << 8) | in[i];
    }
    memcpy(&value, &v, sizeof value);
    return value;
}

static size_t state_bytes(int32_t k, int32_t window)
{
    return 8u * RECURSIVE_STATE_HEADER_WORDS +
           4u * (size_t)(2 * RECURSIVE_N_PARAMS + 4 * k + k * k + 2 * window + 2);
}

size_t recursive_save_state(const recursive_state_t *state, uint8_t *blob, size_t capacity)
{
    const int32_t k = state->k, window = state->window;
    const size_t total = state_bytes(k, window);
    int64_t header[RECURSIVE_STATE_HEADER_WORDS];
    int64_t mask = 0;
    size_t pos;
    int32_t i;
    if (capacity < total) {
        return 0u;
    }
    for (i = 0; i < k; ++i) {
        mask |= (int64_t)1 << state->idx[i];
    }
    header[0] = RECURSIVE_STATE_MAGIC;
    header[1] = RECURSIVE_STATE_VERSION;
    header[2] = 4;
    header[3] = k;
    header[4] = mask;
    header[5] = state->frames;
    header[6] = state->updates;
    header[7] = state->drift_on;
    header[8] = state->drift_frame;
    header[9] = state->ring_pos;
    header[10] = state->ring_count;
    header[11] = window;
    header[12] = state->nis_count;
    header[13] = state->inconsistent_run;
    for (i = 0; i < RECURSIVE_STATE_HEADER_WORDS; ++i) {
        put_i64(&blob[8 * i], header[i]);
    }
    pos = 8u * RECURSIVE_STATE_HEADER_WORDS;
#define PUT(value)                                                                                                   \
    do {                                                                                                             \
        put_f32(&blob[pos], (value));                                                                                \
        pos += 4u;                                                                                                   \
    } while (0)
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) PUT(state->theta_nom[i]);
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) PUT(state->scale[i]);
    for (i = 0; i < k; ++i) PUT(state->x_hi[i]);
    for (i = 0; i < k; ++i) PUT(state->x_lo[i]);
    for (i = 0; i < k * k; ++i) PUT(state->u[i]);
    for (i = 0; i < k; ++i) PUT(state->d[i]);
    for (i = 0; i < k; ++i) PUT(state->q[i]);
    for (i = 0; i < window; ++i) PUT(state->ring_g[i]);
    for (i = 0; i < window; ++i) PUT(state->ring_v[i]);
    PUT((float)state->nis_sum);
    PUT((float)state->q_drift);
#undef PUT
    return pos;
}

recursive_status_t recursive_restore_state(recursive_state_t *state, const uint8_t *blob, size_t length,
                                           const recursive_camera_t *nominal, const recursive_config_t *config)
{
    int64_t header[RECURSIVE_STATE_HEADER_WORDS], mask, window_cfg;
    int32_t k, window, i, bits = 0;
    size_t pos;
    float theta_nom[RECURSIVE_N_PARAMS];
    if (length < 8u * RECURSIVE_STATE_HEADER_WORDS) {
        return RECURSIVE_ERR_STATE;
    }
    for (i = 0; i < RECURSIVE_STATE_HEADER_WORDS; ++i) {
        header[i] = get_i64(&blob[8 * i]);
    }
    if (header[0] != RECURSIVE_STATE_MAGIC || header[1] != RECURSIVE_STATE_VERSION || header[2] != 4) {
        return RECURSIVE_ERR_STATE; /* not a state, another version, or not float32 */
    }
    mask = header[4];
    if (header[3] < 1 || header[3] > RECURSIVE_MAX_STATES || mask < 1 || mask > 0x3ff) {
        return RECURSIVE_ERR_STATE;
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        bits += (int32_t)((mask >> i) & 1);
    }
    k = (int32_t)header[3];
    window_cfg = config->drift_window_frames > 1 ? config->drift_window_frames : 1;
    if (bits != k || header[11] != window_cfg || header[11] > RECURSIVE_MAX_DRIFT_WINDOW) {
        return RECURSIVE_ERR_STATE;
    }
    window = (int32_t)header[11];
    if (length != state_bytes(k, window)) {
        return RECURSIVE_ERR_STATE;
    }
    if (recursive_create(state, nominal, (uint32_t)mask, config) != RECURSIVE_OK) {
        return RECURSIVE_ERR_STATE;
    }
    pos = 8u * RECURSIVE_STATE_HEADER_WORDS;
#define GET() (pos += 4u, get_f32(&blob[pos - 4u]))
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        theta_nom[i] = GET();
        if (theta_nom[i] != state->theta_nom[i]) {
            return RECURSIVE_ERR_STATE; /* saved against a different nominal */
        }
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) state->scale[i] = GET();
    for (i = 0; i < k; ++i) state->x_hi[i] = GET();
    for (i = 0; i < k; ++i) state->x_lo[i] = GET();
    for (i = 0; i < k * k; ++i) state->u[i] = GET();
    for (i = 0; i < k; ++i) state->d[i] = GET();
    for (i = 0; i < k; ++i) state->q[i] = GET();
    for (i = 0; i < window; ++i) state->ring_g[i] = GET();
    for (i = 0; i < window; ++i) state->ring_v[i] = GET();
    state->nis_sum = (double)GET();
    state->q_drift = (double)GET();
#undef GET
    state->frames = header[5];
    state->updates = header[6];
    state->drift_on = header[7] != 0;
    state->drift_frame = header[8];
    state->ring_pos = (int32_t)header[9];
    state->ring_count = (int32_t)header[10];
    state->nis_count = header[12];
    state->inconsistent_run = (int32_t)header[13];
    if (state->ring_pos < 0 || state->ring_pos >= window || state->ring_count < 0 || state->ring_count > window) {
        return RECURSIVE_ERR_STATE;
    }
    for (i = 0; i < k; ++i) {
        if (!isfinite(state->x_hi[i]) || !(state->d[i] > 0.0f)) {
            return RECURSIVE_ERR_STATE; /* corrupt values */
        }
    }
    return RECURSIVE_OK;
}
