/* SIL harness of the C numerical core (onboard/c), compiled by tests/test_c_sil_sanitizers.py with AddressSanitizer
 * and UndefinedBehaviorSanitizer (any finding aborts). Reads commands on stdin, one per line, numbers as C99 hex
 * floats (%a, exact) or decimal integers; writes each result on one line ("O ..."). Test code, not part of the core.
 *
 *   P n theta[10] x[n] y[n]                       camera_pixels_to_unit              -> b[n][3]
 *   J n theta[10] x[n] y[n]                       camera_unit_vector_jacobians       -> b, j_theta, j_centroid
 *   F w h theta[10] n xq[n] yq[n]                 fixedpoint_camera + pixels_to_unit -> s x0_q y0_q qw f_w b_q30[n][3]
 *   E p n b_q30[n][3] r_q30[n][3] pi[p] pj[p]     fixedpoint_difference_residuals_q61 -> e[p]
 *   U k u[k*k] d[k] xi[k] h[k] y                  ud_bierman_update                  -> u d xi innovation s
 *   R n r[n][3] zen[3] beta[3] a b with           refraction_topocentric_observed_q30 -> out[n][3]
 *   A n r0[n][3] pm[n][3] plx[n] years eb[3] e[3] k beta[3] tod[9]  apparent_place_vectors_q30 -> out[n][3]
 *   T n b[n][3] r[n][3] w[n]                      attitude_from_vectors              -> status c[9]
 *   G n r0[n][3] pm[n][3] plx[n] epoch day frac   apparent_place_vectors (float32)   -> tod[9] out[n][3]
 *   C f_mm pitch x0 y0 w h dist[7] mask           recursive_create (default config)
 *   X fixed n x[n] y[n] r[n][3] ident[n]          recursive_update(_fixed) (x, y, r as double; fixed: Q10/Q30)
 *   Z                                             recursive_save_state               -> bytes (hex) */
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "apparent.h"
#include "attitude.h"
#include "camera.h"
#include "earth.h"
#include "fixedpoint.h"
#include "recursive.h"
#include "refraction.h"
#include "ud.h"

#define MAX_N 256

static double num(void)
{
    char tok[64];
    if (scanf("%63s", tok) != 1) {
        exit(3);
    }
    return strtod(tok, NULL);
}

static int64_t inum(void)
{
    char tok[64];
    if (scanf("%63s", tok) != 1) {
        exit(3);
    }
    return (int64_t)strtoll(tok, NULL, 10);
}

static size_t count(void)
{
    const int64_t n = inum();
    if (n < 0 || n > MAX_N) {
        exit(4);
    }
    return (size_t)n;
}

static void fl(float v)
{
    printf(" %a", (double)v);
}

static recursive_state_t state;
static uint8_t blob[RECURSIVE_STATE_MAX_BYTES];

int main(void)
{
    char op[8];
    static float x[MAX_N], y[MAX_N], theta[10], b[MAX_N][3], r[MAX_N][3], w[MAX_N];
    static float jt[MAX_N][3][10], jc[MAX_N][3][2];
    static int64_t xq[MAX_N], yq[MAX_N], bq[MAX_N][3], rq[MAX_N][3], e[MAX_N], pmq[MAX_N][3], plx[MAX_N];
    static int32_t pi[MAX_N], pj[MAX_N];
    static uint8_t ident[MAX_N];
    size_t n, i, k;
    int c;
    while (scanf("%7s", op) == 1) {
        printf("O");
        if (op[0] == 'P' || op[0] == 'J') {
            n = count();
            for (i = 0u; i < 10u; ++i) theta[i] = (float)num();
            for (i = 0u; i < n; ++i) x[i] = (float)num();
            for (i = 0u; i < n; ++i) y[i] = (float)num();
            if (op[0] == 'P') {
                camera_pixels_to_unit(x, y, n, theta, b);
                for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) fl(b[i][c]);
            } else {
                camera_unit_vector_jacobians(x, y, n, theta, b, jt, jc);
                for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) fl(b[i][c]);
                for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) for (k = 0u; k < 10u; ++k) fl(jt[i][c][k]);
                for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) for (k = 0u; k < 2u; ++k) fl(jc[i][c][k]);
            }
        } else if (op[0] == 'F') {
            fixedpoint_camera_t cam;
            const int32_t wpx = (int32_t)inum(), hpx = (int32_t)inum();
            for (i = 0u; i < 10u; ++i) theta[i] = (float)num();
            n = count();
            for (i = 0u; i < n; ++i) xq[i] = inum();
            for (i = 0u; i < n; ++i) yq[i] = inum();
            if (fixedpoint_camera(theta, wpx, hpx, &cam) != FIXEDPOINT_OK) {
                printf(" refused\n");
                continue;
            }
            printf(" %" PRId32 " %" PRId64 " %" PRId64 " %" PRId32 " %" PRId64, cam.s, cam.x0_q, cam.y0_q, cam.qw, cam.f_w);
            for (i = 0u; i < n; ++i) {
                if (fixedpoint_pixels_to_unit_q30(xq[i], yq[i], &cam, bq[i]) != FIXEDPOINT_OK) {
                    bq[i][0] = bq[i][1] = bq[i][2] = 0;
                }
                for (c = 0; c < 3; ++c) printf(" %" PRId64, bq[i][c]);
            }
        } else if (op[0] == 'E') {
            const size_t p = count();
            n = count();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) bq[i][c] = inum();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) rq[i][c] = inum();
            for (i = 0u; i < p; ++i) pi[i] = (int32_t)inum();
            for (i = 0u; i < p; ++i) pj[i] = (int32_t)inum();
            fixedpoint_difference_residuals_q61((const int64_t (*)[3])bq, (const int64_t (*)[3])rq, pi, pj, p, e);
            for (i = 0u; i < p; ++i) printf(" %" PRId64, e[i]);
        } else if (op[0] == 'U') {
            float u[UD_MAX_STATES * UD_MAX_STATES], d[UD_MAX_STATES], xi[UD_MAX_STATES], h[UD_MAX_STATES], s, innov;
            k = count();
            if (k > UD_MAX_STATES) return 4;
            for (i = 0u; i < k * k; ++i) u[i] = (float)num();
            for (i = 0u; i < k; ++i) d[i] = (float)num();
            for (i = 0u; i < k; ++i) xi[i] = (float)num();
            for (i = 0u; i < k; ++i) h[i] = (float)num();
            innov = ud_bierman_update(u, d, xi, h, (float)num(), k, &s);
            for (i = 0u; i < k * k; ++i) fl(u[i]);
            for (i = 0u; i < k; ++i) fl(d[i]);
            for (i = 0u; i < k; ++i) fl(xi[i]);
            fl(innov);
            fl(s);
        } else if (op[0] == 'R') {
            int64_t zen[3], beta[3], a, bb, out[MAX_N][3];
            int with;
            n = count();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) rq[i][c] = inum();
            for (c = 0; c < 3; ++c) zen[c] = inum();
            for (c = 0; c < 3; ++c) beta[c] = inum();
            a = inum();
            bb = inum();
            with = (int)inum();
            refraction_topocentric_observed_q30((const int64_t (*)[3])rq, n, zen, beta, with, a, bb, out);
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) printf(" %" PRId64, out[i][c]);
        } else if (op[0] == 'A') {
            apparent_instant_t inst;
            int64_t out[MAX_N][3];
            n = count();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) rq[i][c] = inum();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) pmq[i][c] = inum();
            for (i = 0u; i < n; ++i) plx[i] = inum();
            inst.years_q20 = inum();
            for (c = 0; c < 3; ++c) inst.earth_bary_q30[c] = inum();
            for (c = 0; c < 3; ++c) inst.sun_to_earth_q30[c] = inum();
            inst.deflection_k_q70 = inum();
            for (c = 0; c < 3; ++c) inst.beta_q44[c] = inum();
            for (c = 0; c < 9; ++c) inst.tod_q30[c / 3][c % 3] = inum();
            apparent_place_vectors_q30((const int64_t (*)[3])rq, (const int64_t (*)[3])pmq, plx, n, &inst, out);
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) printf(" %" PRId64, out[i][c]);
        } else if (op[0] == 'T') {
            float cm[3][3];
            attitude_status_t status;
            n = count();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) b[i][c] = (float)num();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) r[i][c] = (float)num();
            for (i = 0u; i < n; ++i) w[i] = (float)num();
            status = attitude_from_vectors((const float (*)[3])b, (const float (*)[3])r, w, n, cm);
            printf(" %d", (int)status);
            for (c = 0; c < 9; ++c) fl(cm[c / 3][c % 3]);
        } else if (op[0] == 'G') {
            static float pmf[MAX_N][3], plxf[MAX_N], out[MAX_N][3];
            float tod[3][3];
            timescale_time_t t;
            double epoch;
            n = count();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) r[i][c] = (float)num();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) pmf[i][c] = (float)num();
            for (i = 0u; i < n; ++i) plxf[i] = (float)num();
            epoch = num();
            t.day = (int32_t)inum();
            t.frac = (uint32_t)inum();
            earth_true_of_date_matrix(t, tod);
            apparent_place_vectors((const float (*)[3])r, (const float (*)[3])pmf, plxf, n, epoch, t, out);
            for (c = 0; c < 9; ++c) fl(tod[c / 3][c % 3]);
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) fl(out[i][c]);
        } else if (op[0] == 'C') {
            recursive_camera_t cam;
            recursive_config_t cfg;
            cam.focal_length_mm = num();
            cam.pixel_pitch_um = num();
            cam.principal_point_px[0] = num();
            cam.principal_point_px[1] = num();
            cam.image_size_px[0] = (int32_t)inum();
            cam.image_size_px[1] = (int32_t)inum();
            for (c = 0; c < 7; ++c) cam.distortion[c] = num();
            recursive_default_config(&cfg);
            printf(" %d", (int)recursive_create(&state, &cam, (uint32_t)inum(), &cfg));
        } else if (op[0] == 'X') {
            recursive_frame_result_t res;
            recursive_status_t status;
            const int fixed = (int)inum();
            static double xd[MAX_N], yd[MAX_N], rd[MAX_N][3];
            n = count();
            for (i = 0u; i < n; ++i) xd[i] = num();
            for (i = 0u; i < n; ++i) yd[i] = num();
            for (i = 0u; i < n; ++i) for (c = 0; c < 3; ++c) rd[i][c] = num();
            for (i = 0u; i < n; ++i) ident[i] = (uint8_t)inum();
            if (fixed) {
                for (i = 0u; i < n; ++i) {
                    xq[i] = fixedpoint_quantise_px(xd[i]);
                    yq[i] = fixedpoint_quantise_px(yd[i]);
                    for (c = 0; c < 3; ++c) rq[i][c] = ident[i] ? fixedpoint_quantise_unit_q30(rd[i][c]) : 0;
                }
                status = recursive_update_fixed(&state, xq, yq, (const int64_t (*)[3])rq, ident, n, &res);
            } else {
                for (i = 0u; i < n; ++i) {
                    x[i] = (float)xd[i];
                    y[i] = (float)yd[i];
                    for (c = 0; c < 3; ++c) r[i][c] = (float)rd[i][c];
                }
                status = recursive_update(&state, x, y, (const float (*)[3])r, ident, n, &res);
            }
            printf(" %d %d %d %d", (int)status, (int)res.skipped, (int)res.n_pairs, (int)res.iterations);
        } else if (op[0] == 'Z') {
            const size_t len = recursive_save_state(&state, blob, sizeof blob);
            printf(" ");
            for (i = 0u; i < len; ++i) printf("%02x", blob[i]);
        } else {
            return 2;
        }
        printf("\n");
    }
    return 0;
}
