/* ud.c: onboard/ud.py in float32 (see ud.h).
 *
 * Operation order (onboard/linalg32.py, docs/port-kit.md "The order"): every float32 sum starts from its first
 * term and adds the others in index order, every product and sum rounded on its own (-ffp-contract=off), as the
 * reference model does; keep it, and the results are the model's bits. */
#include "ud.h"

float ud_bierman_update(float *u, float *d, float *xi, const float *h, float y, size_t k, float *s)
{
    float f[UD_MAX_STATES], v[UD_MAX_STATES], alpha[UD_MAX_STATES], ap[UD_MAX_STATES];
    float cols[UD_MAX_STATES * UD_MAX_STATES];
    float innovation, dot, gain;
    size_t i, j;
    for (j = 0u; j < k; ++j) { /* f = U^T h */
        float acc = h[0] * u[j];
        for (i = 1u; i < k; ++i) {
            acc += h[i] * u[i * k + j];
        }
        f[j] = acc;
    }
    for (j = 0u; j < k; ++j) {
        v[j] = d[j] * f[j]; /* v = D f */
        alpha[j] = f[j] * v[j];
        if (j > 0u) {
            alpha[j] += alpha[j - 1u];
        }
    }
    for (j = 0u; j < k; ++j) {
        alpha[j] += 1.0f; /* alpha_j = 1 + sum_{i<=j} f_i v_i (R = 1 after whitening) */
    }
    ap[0] = 1.0f;
    for (j = 1u; j < k; ++j) {
        ap[j] = alpha[j - 1u];
    }
    *s = alpha[k - 1u];
    dot = h[0] * xi[0];
    for (j = 1u; j < k; ++j) {
        dot += h[j] * xi[j];
    }
    innovation = y - dot;
    for (j = 0u; j < k; ++j) { /* d_j' = d_j alpha_{j-1} / alpha_j */
        d[j] *= ap[j];
        d[j] /= alpha[j];
    }
    /* b_j = sum_{l<=j} v_l U_l (old columns); U_j' = U_j + lambda_j b_{j-1}, lambda_j = -f_j / alpha_{j-1} */
    for (i = 0u; i < k; ++i) {
        for (j = 0u; j < k; ++j) {
            cols[i * k + j] = u[i * k + j] * v[j];
            if (j > 0u) {
                cols[i * k + j] += cols[i * k + j - 1u];
            }
        }
    }
    gain = innovation / *s;
    for (i = 0u; i < k; ++i) {
        xi[i] += cols[i * k + k - 1u] * gain; /* gain = b_K / alpha_K */
    }
    for (j = 0u; j < k; ++j) {
        f[j] /= ap[j]; /* f now holds -lambda */
    }
    for (i = 0u; i < k; ++i) {
        for (j = 0u; j + 1u < k; ++j) {
            cols[i * k + j] *= f[j + 1u];
        }
        for (j = 1u; j < k; ++j) {
            u[i * k + j] -= cols[i * k + j - 1u];
        }
    }
    return innovation;
}

void ud_agee_turner_update(float *u, float *d, float *a, float c, size_t k)
{
    size_t last = k, j, i;
    for (j = 0u; j < k; ++j) {
        if (a[j] != 0.0f) {
            last = j;
        }
    }
    if (last == k || !(c > 0.0f)) {
        return;
    }
    for (j = last + 1u; j-- > 0u;) {
        const float aj = a[j];
        float dj, dj_new, ratio, weight;
        if (aj == 0.0f) {
            continue;
        }
        dj = d[j];
        dj_new = dj + c * aj * aj;
        ratio = dj / dj_new;
        weight = c * aj / dj_new;
        for (i = 0u; i < j; ++i) {
            const float col = u[i * k + j];
            const float tmp = a[i] - aj * col;
            u[i * k + j] = col * ratio + weight * a[i];
            a[i] = tmp;
        }
        c = c * dj / dj_new;
        d[j] = dj_new;
    }
}

void ud_covariance(const float *u, const float *d, size_t k, double *p)
{
    size_t i, j, l;
    for (i = 0u; i < k; ++i) {
        for (j = 0u; j < k; ++j) {
            double acc = 0.0;
            for (l = 0u; l < k; ++l) {
                acc += (double)u[i * k + l] * (double)d[l] * (double)u[j * k + l];
            }
            p[i * k + j] = acc;
        }
    }
}
