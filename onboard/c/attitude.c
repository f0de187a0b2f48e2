/* attitude.c: onboard/attitude.py's attitude_from_vectors in float32 (see attitude.h). */
#include "attitude.h"

#include <math.h>

/* Eigen-decomposition of the symmetric 3 x 3 a by cyclic Jacobi rotations: eigenvalues in eig (descending),
 * eigenvectors in the columns of v (a right-handed or left-handed orthonormal basis). */
static void jacobi3(float a[3][3], float eig[3], float v[3][3])
{
    int sweep, p, q, k, i, j;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            v[i][j] = i == j ? 1.0f : 0.0f;
        }
    }
    for (sweep = 0; sweep < ATTITUDE_JACOBI_SWEEPS; ++sweep) {
        for (p = 0; p < 2; ++p) {
            for (q = p + 1; q < 3; ++q) {
                float theta, t, cs, sn;
                if (a[p][q] == 0.0f) {
                    continue;
                }
                /* the rotation that zeroes a[p][q]: t = tan(angle), the smaller root of t^2 + 2 theta t - 1 = 0 */
                theta = (a[q][q] - a[p][p]) / (2.0f * a[p][q]);
                t = 1.0f / (fabsf(theta) + sqrtf(theta * theta + 1.0f));
                if (theta < 0.0f) {
                    t = -t;
                }
                cs = 1.0f / sqrtf(t * t + 1.0f);
                sn = t * cs;
                for (k = 0; k < 3; ++k) { /* a <- a J (columns p, q) */
                    const float akp = a[k][p], akq = a[k][q];
                    a[k][p] = cs * akp - sn * akq;
                    a[k][q] = sn * akp + cs * akq;
                }
                for (k = 0; k < 3; ++k) { /* a <- J^T a (rows p, q) */
                    const float apk = a[p][k], aqk = a[q][k];
                    a[p][k] = cs * apk - sn * aqk;
                    a[q][k] = sn * apk + cs * aqk;
                }
                for (k = 0; k < 3; ++k) {
                    const float vkp = v[k][p], vkq = v[k][q];
                    v[k][p] = cs * vkp - sn * vkq;
                    v[k][q] = sn * vkp + cs * vkq;
                }
            }
        }
    }
    for (i = 0; i < 3; ++i) {
        eig[i] = a[i][i];
    }
    for (i = 0; i < 2; ++i) { /* sort descending (selection sort of three) */
        int best = i;
        for (j = i + 1; j < 3; ++j) {
            if (eig[j] > eig[best]) {
                best = j;
            }
        }
        if (best != i) {
            const float te = eig[i];
            eig[i] = eig[best];
            eig[best] = te;
            for (k = 0; k < 3; ++k) {
                const float tv = v[k][i];
                v[k][i] = v[k][best];
                v[k][best] = tv;
            }
        }
    }
}

static void cross3(const float a[3], const float b[3], float out[3])
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

void attitude_small_rotation(const float phi[3], float out[3][3])
{
    const float angle2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2];
    const float s = 1.0f - angle2 / 6.0f + angle2 * angle2 / 120.0f;
    const float k = 0.5f - angle2 / 24.0f + angle2 * angle2 / 720.0f;
    const float x[3][3] = {{0.0f, -phi[2], phi[1]}, {phi[2], 0.0f, -phi[0]}, {-phi[1], phi[0], 0.0f}};
    int i, j, m;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            float xx = 0.0f;
            for (m = 0; m < 3; ++m) {
                xx += x[i][m] * x[m][j];
            }
            out[i][j] = (i == j ? 1.0f : 0.0f) + s * x[i][j] + k * xx;
        }
    }
}

/* One Gauss-Newton step on Wahba's loss about c: phi = (sum w (I - p p^T))^-1 sum w p x (b - p), p = C r. */
static void refine(const float (*b)[3], const float (*r)[3], const float *weights, size_t n, float c[3][3])
{
    float info[3][3] = {{0.0f}}, g[3] = {0.0f}, l[3][3] = {{0.0f}}, y[3], phi[3], rot[3][3], out[3][3];
    size_t i;
    int j, k, m;
    for (i = 0u; i < n; ++i) {
        const float w = weights != NULL ? weights[i] : 1.0f;
        float p[3], d[3], px[3];
        for (j = 0; j < 3; ++j) {
            p[j] = c[j][0] * r[i][0] + c[j][1] * r[i][1] + c[j][2] * r[i][2];
        }
        for (j = 0; j < 3; ++j) {
            d[j] = b[i][j] - p[j];
            for (k = 0; k < 3; ++k) {
                info[j][k] += w * ((j == k ? 1.0f : 0.0f) - p[j] * p[k]);
            }
        }
        cross3(p, d, px);
        for (j = 0; j < 3; ++j) {
            g[j] += w * px[j];
        }
    }
    /* info is symmetric positive definite for two or more non-parallel stars: Cholesky, two substitutions */
    for (j = 0; j < 3; ++j) {
        float diag = info[j][j];
        for (m = 0; m < j; ++m) {
            diag -= l[j][m] * l[j][m];
        }
        l[j][j] = sqrtf(diag);
        for (k = j + 1; k < 3; ++k) {
            float v = info[k][j];
            for (m = 0; m < j; ++m) {
                v -= l[k][m] * l[j][m];
            }
            l[k][j] = v / l[j][j];
        }
    }
    for (j = 0; j < 3; ++j) {
        float v = g[j];
        for (m = 0; m < j; ++m) {
            v -= l[j][m] * y[m];
        }
        y[j] = v / l[j][j];
    }
    for (j = 2; j >= 0; --j) {
        float v = y[j];
        for (m = j + 1; m < 3; ++m) {
            v -= l[m][j] * phi[m];
        }
        phi[j] = v / l[j][j];
    }
    attitude_small_rotation(phi, rot);
    for (j = 0; j < 3; ++j) {
        for (k = 0; k < 3; ++k) {
            out[j][k] = rot[j][0] * c[0][k] + rot[j][1] * c[1][k] + rot[j][2] * c[2][k];
        }
    }
    for (j = 0; j < 3; ++j) {
        for (k = 0; k < 3; ++k) {
            c[j][k] = out[j][k];
        }
    }
}

attitude_status_t attitude_from_vectors(const float (*b)[3], const float (*r)[3], const float *weights, size_t n,
                                        float c[3][3])
{
    float profile[3][3] = {{0.0f}}, btb[3][3], eig[3], v[3][3], u[3][3], s[2], dot, norm, det_v;
    size_t i;
    int j, k, m, step;
    if (n < 2u) {
        return ATTITUDE_ERR_DEGENERATE;
    }
    for (i = 0u; i < n; ++i) { /* B = sum w b r^T */
        const float w = weights != NULL ? weights[i] : 1.0f;
        for (j = 0; j < 3; ++j) {
            for (k = 0; k < 3; ++k) {
                profile[j][k] += (b[i][j] * w) * r[i][k];
            }
        }
    }
    for (j = 0; j < 3; ++j) {
        for (k = 0; k < 3; ++k) {
            btb[j][k] = 0.0f;
            for (m = 0; m < 3; ++m) {
                btb[j][k] += profile[m][j] * profile[m][k];
            }
        }
    }
    jacobi3(btb, eig, v);
    s[0] = sqrtf(eig[0] > 0.0f ? eig[0] : 0.0f);
    s[1] = sqrtf(eig[1] > 0.0f ? eig[1] : 0.0f);
    if (!(s[1] > s[0] * ATTITUDE_COLLINEAR_RATIO)) {
        return ATTITUDE_ERR_DEGENERATE;
    }
    for (k = 0; k < 2; ++k) { /* u_k = B v_k / s_k */
        for (j = 0; j < 3; ++j) {
            u[j][k] = (profile[j][0] * v[0][k] + profile[j][1] * v[1][k] + profile[j][2] * v[2][k]) / s[k];
        }
    }
    /* u_1 orthogonalised against u_0 and both normalised (the small singular value's vector is the least exact) */
    for (k = 0; k < 2; ++k) {
        if (k == 1) {
            dot = u[0][0] * u[0][1] + u[1][0] * u[1][1] + u[2][0] * u[2][1];
            for (j = 0; j < 3; ++j) {
                u[j][1] -= dot * u[j][0];
            }
        }
        norm = sqrtf(u[0][k] * u[0][k] + u[1][k] * u[1][k] + u[2][k] * u[2][k]);
        for (j = 0; j < 3; ++j) {
            u[j][k] /= norm;
        }
    }
    {
        const float u0[3] = {u[0][0], u[1][0], u[2][0]}, u1[3] = {u[0][1], u[1][1], u[2][1]};
        float u2[3];
        cross3(u0, u1, u2); /* det U = +1 by construction */
        for (j = 0; j < 3; ++j) {
            u[j][2] = u2[j];
        }
    }
    det_v = v[0][0] * (v[1][1] * v[2][2] - v[1][2] * v[2][1]) - v[0][1] * (v[1][0] * v[2][2] - v[1][2] * v[2][0]) +
            v[0][2] * (v[1][0] * v[2][1] - v[1][1] * v[2][0]);
    /* C = U diag(1, 1, det U det V) V^T (Markley 1988) */
    for (j = 0; j < 3; ++j) {
        for (k = 0; k < 3; ++k) {
            c[j][k] = u[j][0] * v[k][0] + u[j][1] * v[k][1] + (det_v < 0.0f ? -1.0f : 1.0f) * u[j][2] * v[k][2];
        }
    }
    for (step = 0; step < ATTITUDE_REFINEMENT_STEPS; ++step) {
        refine(b, r, weights, n, c);
    }
    return ATTITUDE_OK;
}
