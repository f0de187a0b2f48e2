/* camera.c: onboard/camera.py in float32 (see camera.h).
 *
 * Operation order (onboard/linalg32.py, docs/port-kit.md "The order"): every float32 sum starts from its first
 * term and adds the others in index order, every product and sum rounded on its own (-ffp-contract=off), as the
 * reference model does; keep it, and the results are the model's bits. */
#include "camera.h"

#include <math.h>

void camera_distortion_px(float u, float v, const float theta[CAMERA_N_PARAMS], float *dx, float *dy)
{
    const float k1 = theta[3], k2 = theta[4], k3 = theta[5], p1 = theta[6], p2 = theta[7], s1 = theta[8];
    const float s2 = theta[9];
    const float g1 = s1 + p1, g2 = s2 + p2, g3 = p1 + p1, g4 = p2 + p2;
    const float r2 = u * u + v * v;
    const float radial = r2 * (k1 + r2 * (k2 + r2 * k3));
    *dx = (g1 + g3) * u * u + g4 * u * v + g1 * v * v + u * radial;
    *dy = g2 * u * u + g3 * u * v + (g2 + g4) * v * v + v * radial;
}

void camera_distortion_partials(float u, float v, const float theta[CAMERA_N_PARAMS], float *dx_u, float *dx_v,
                                float *dy_u, float *dy_v)
{
    const float k1 = theta[3], k2 = theta[4], k3 = theta[5], p1 = theta[6], p2 = theta[7], s1 = theta[8];
    const float s2 = theta[9];
    const float two = 2.0f, three = 3.0f;
    const float g1 = s1 + p1, g2 = s2 + p2, g3 = p1 + p1, g4 = p2 + p2;
    const float r2 = u * u + v * v;
    const float radial = r2 * (k1 + r2 * (k2 + r2 * k3));
    const float radial_d = k1 + r2 * (two * k2 + three * k3 * r2); /* d radial / d r2 */
    *dx_u = two * (g1 + g3) * u + g4 * v + radial + two * u * u * radial_d;
    *dx_v = g4 * u + two * g1 * v + two * u * v * radial_d;
    *dy_u = two * g2 * u + g3 * v + two * u * v * radial_d;
    *dy_v = g3 * u + two * (g2 + g4) * v + radial + two * v * v * radial_d;
}

void camera_ideal_offsets(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                          float *u_ideal_px, float *v_ideal_px)
{
    size_t i;
    for (i = 0u; i < n; ++i) {
        const float u = x_px[i] - theta[1];
        const float v = y_px[i] - theta[2];
        float dx, dy;
        camera_distortion_px(u, v, theta, &dx, &dy);
        u_ideal_px[i] = u - dx;
        v_ideal_px[i] = v - dy;
    }
}

void camera_offsets_to_unit(const float *u_ideal_px, const float *v_ideal_px, size_t n, float focal_px,
                            float (*b)[3])
{
    size_t i;
    for (i = 0u; i < n; ++i) {
        const float u = u_ideal_px[i], v = v_ideal_px[i];
        const float norm = sqrtf(u * u + v * v + focal_px * focal_px);
        b[i][0] = u / norm;
        b[i][1] = v / norm;
        b[i][2] = focal_px / norm;
    }
}

void camera_pixels_to_unit(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                           float (*b)[3])
{
    size_t i;
    for (i = 0u; i < n; ++i) {
        float u, v;
        camera_ideal_offsets(&x_px[i], &y_px[i], 1u, theta, &u, &v);
        camera_offsets_to_unit(&u, &v, 1u, theta[0], &b[i]);
    }
}

void camera_unit_vector_jacobians(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                                  float (*b)[3], float (*j_theta)[3][CAMERA_N_PARAMS], float (*j_centroid)[3][2])
{
    size_t i;
    int c, m, k;
    for (i = 0u; i < n; ++i) {
        /* ideal_offset_jacobians */
        const float u = x_px[i] - theta[1];
        const float v = y_px[i] - theta[2];
        float dx, dy, dx_u, dx_v, dy_u, dy_v;
        float jq[2][CAMERA_N_PARAMS] = {{0.0f}};
        float jqc[2][2];
        float w[3], proj[3][3], jw[3][CAMERA_N_PARAMS] = {{0.0f}};
        float r2, r4, r6, uu, uv, vv, norm;
        camera_distortion_px(u, v, theta, &dx, &dy);
        camera_distortion_partials(u, v, theta, &dx_u, &dx_v, &dy_u, &dy_v);
        r2 = u * u + v * v;
        jq[0][1] = -(1.0f - dx_u); /* principal point: u = x - x0, d/dx0 = -d/du */
        jq[0][2] = dx_v;
        jq[1][1] = dy_u;
        jq[1][2] = -(1.0f - dy_v);
        r4 = r2 * r2;
        r6 = r4 * r2;
        jq[0][3] = -u * r2;
        jq[0][4] = -u * r4;
        jq[0][5] = -u * r6;
        jq[1][3] = -v * r2;
        jq[1][4] = -v * r4;
        jq[1][5] = -v * r6;
        uu = u * u;
        uv = u * v;
        vv = v * v;
        jq[0][6] = -(3.0f * uu + vv); /* p1 */
        jq[1][6] = -2.0f * uv;
        jq[0][7] = -2.0f * uv; /* p2 */
        jq[1][7] = -(uu + 3.0f * vv);
        jq[0][8] = -(uu + vv); /* s1 */
        jq[1][9] = -(uu + vv); /* s2 */
        jqc[0][0] = 1.0f - dx_u;
        jqc[0][1] = -dx_v;
        jqc[1][0] = -dy_u;
        jqc[1][1] = 1.0f - dy_v;
        /* unit_vector_jacobians */
        w[0] = u - dx;
        w[1] = v - dy;
        w[2] = theta[0];
        norm = sqrtf(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
        for (c = 0; c < 3; ++c) {
            b[i][c] = w[c] / norm;
        }
        for (c = 0; c < 3; ++c) {
            for (m = 0; m < 3; ++m) {
                proj[c][m] = ((c == m ? 1.0f : 0.0f) - b[i][c] * b[i][m]) / norm;
            }
        }
        for (k = 0; k < CAMERA_N_PARAMS; ++k) {
            jw[0][k] = jq[0][k];
            jw[1][k] = jq[1][k];
        }
        jw[2][0] = 1.0f;
        for (c = 0; c < 3; ++c) {
            for (k = 0; k < CAMERA_N_PARAMS; ++k) {
                float acc = proj[c][0] * jw[0][k];
                for (m = 1; m < 3; ++m) {
                    acc += proj[c][m] * jw[m][k];
                }
                j_theta[i][c][k] = acc;
            }
            for (k = 0; k < 2; ++k) {
                j_centroid[i][c][k] = proj[c][0] * jqc[0][k] + proj[c][1] * jqc[1][k];
            }
        }
    }
}
