/* interstar.c: onboard/interstar.py in float32 (see interstar.h).
 *
 * Operation order (onboard/linalg32.py, docs/port-kit.md "The order"): every float32 sum starts from its first
 * term and adds the others in index order, every product and sum rounded on its own (-ffp-contract=off), as the
 * reference model does; keep it, and the results are the model's bits. */
#include "interstar.h"

size_t interstar_independent_pairs(size_t n_stars, int32_t *pi, int32_t *pj)
{
    size_t k, p = 0u;
    if (n_stars < 2u) {
        return 0u;
    }
    pi[p] = 0;
    pj[p] = 1;
    ++p;
    for (k = 2u; k < n_stars; ++k, ++p) {
        pi[p] = 0;
        pj[p] = (int32_t)k;
    }
    for (k = 2u; k < n_stars; ++k, ++p) {
        pi[p] = 1;
        pj[p] = (int32_t)k;
    }
    return p;
}

void interstar_order_for_pairs(const float *x_px, const float *y_px, size_t n, int32_t *order)
{
    float mx, my, best;
    size_t i, a = 0u, b = 0u, p;
    for (i = 0u; i < n; ++i) {
        order[i] = (int32_t)i;
    }
    if (n < 3u) {
        return;
    }
    mx = x_px[0];
    my = y_px[0];
    for (i = 1u; i < n; ++i) {
        mx += x_px[i];
        my += y_px[i];
    }
    mx /= (float)n;
    my /= (float)n;
    best = -1.0f;
    for (i = 0u; i < n; ++i) { /* first maximum, as argmax */
        const float dx = x_px[i] - mx, dy = y_px[i] - my;
        const float d0 = dx * dx + dy * dy;
        if (d0 > best) {
            best = d0;
            a = i;
        }
    }
    best = -1.0f;
    for (i = 0u; i < n; ++i) {
        const float dx = x_px[i] - x_px[a], dy = y_px[i] - y_px[a];
        const float d1 = dx * dx + dy * dy;
        if (d1 > best) {
            best = d1;
            b = i;
        }
    }
    if (b == a) {
        b = a == 0u ? 1u : 0u;
    }
    order[0] = (int32_t)a;
    order[1] = (int32_t)b;
    p = 2u;
    for (i = 0u; i < n; ++i) {
        if (i != a && i != b) {
            order[p++] = (int32_t)i;
        }
    }
}

void interstar_difference_residuals(const float (*b)[3], const float (*r)[3], const int32_t *pi, const int32_t *pj,
                                    size_t n_pairs, float *e)
{
    size_t p;
    for (p = 0u; p < n_pairs; ++p) {
        const float *bi = b[pi[p]], *bj = b[pj[p]], *ri = r[pi[p]], *rj = r[pj[p]];
        const float db0 = bi[0] - bj[0], db1 = bi[1] - bj[1], db2 = bi[2] - bj[2];
        const float dr0 = ri[0] - rj[0], dr1 = ri[1] - rj[1], dr2 = ri[2] - rj[2];
        e[p] = ((db0 * db0 + db1 * db1 + db2 * db2) - (dr0 * dr0 + dr1 * dr1 + dr2 * dr2)) / 2.0f;
    }
}

void interstar_difference_jacobian(const float (*b)[3], const float *jb, size_t k, const int32_t *pi,
                                   const int32_t *pj, size_t n_pairs, float *h)
{
    size_t p, col;
    int c;
    for (p = 0u; p < n_pairs; ++p) {
        const size_t i = (size_t)pi[p], j = (size_t)pj[p];
        for (col = 0u; col < k; ++col) {
            float acc = (b[i][0] - b[j][0]) * (jb[(i * 3u) * k + col] - jb[(j * 3u) * k + col]);
            for (c = 1; c < 3; ++c) {
                const float db = b[i][c] - b[j][c];
                acc += db * (jb[(i * 3u + (size_t)c) * k + col] - jb[(j * 3u + (size_t)c) * k + col]);
            }
            h[p * k + col] = -acc;
        }
    }
}

void interstar_pair_covariance(const float (*b)[3], const float (*jc)[3][2], const int32_t *pi, const int32_t *pj,
                               size_t n_pairs, double sigma_px, float *r)
{
    /* each pair's row of dh/dc has four nonzero entries: -(b_i - b_j)^T Jc_i at star i, +(b_i - b_j)^T Jc_j at j */
    float gi[INTERSTAR_MAX_PAIRS][2], gj[INTERSTAR_MAX_PAIRS][2];
    const float s2 = (float)(sigma_px * sigma_px);
    size_t p, q;
    int c, a;
    for (p = 0u; p < n_pairs; ++p) {
        const size_t i = (size_t)pi[p], j = (size_t)pj[p];
        for (a = 0; a < 2; ++a) {
            float acc_i = (b[i][0] - b[j][0]) * jc[i][0][a], acc_j = (b[i][0] - b[j][0]) * jc[j][0][a];
            for (c = 1; c < 3; ++c) {
                const float db = b[i][c] - b[j][c];
                acc_i += db * jc[i][c][a];
                acc_j += db * jc[j][c][a];
            }
            gi[p][a] = -acc_i;
            gj[p][a] = acc_j;
        }
    }
    for (p = 0u; p < n_pairs; ++p) {
        for (q = 0u; q < n_pairs; ++q) {
            float acc = 0.0f;
            /* sum over the stars the two pairs share (a pair's own two stars are distinct) */
            if (pi[p] == pi[q]) {
                acc += gi[p][0] * gi[q][0] + gi[p][1] * gi[q][1];
            }
            if (pi[p] == pj[q]) {
                acc += gi[p][0] * gj[q][0] + gi[p][1] * gj[q][1];
            }
            if (pj[p] == pi[q]) {
                acc += gj[p][0] * gi[q][0] + gj[p][1] * gi[q][1];
            }
            if (pj[p] == pj[q]) {
                acc += gj[p][0] * gj[q][0] + gj[p][1] * gj[q][1];
            }
            r[p * n_pairs + q] = s2 * acc;
        }
    }
}
