/* refraction.c: onboard/refraction.py's per-star part in float32 and in integers (see refraction.h). */
#include "refraction.h"

#include <math.h>

#include "fixedpoint.h"

void refraction_zenith_geometry(const float (*r)[3], size_t n, const float zenith[3], float *cos_z, float *sin_z,
                                float (*tangential)[3])
{
    size_t i;
    int c;
    for (i = 0u; i < n; ++i) {
        const float cz = r[i][0] * zenith[0] + r[i][1] * zenith[1] + r[i][2] * zenith[2];
        float s2;
        for (c = 0; c < 3; ++c) {
            tangential[i][c] = zenith[c] - cz * r[i][c];
        }
        s2 = tangential[i][0] * tangential[i][0] + tangential[i][1] * tangential[i][1] +
             tangential[i][2] * tangential[i][2];
        cos_z[i] = cz;
        sin_z[i] = sqrtf(s2 > 0.0f ? s2 : 0.0f);
    }
}

float refraction_from_true_zenith(float cos_zt, float sin_zt, double a_rad, double b_rad)
{
    const float a = (float)a_rad, b = (float)b_rad, min_cos = (float)REFRACTION_MIN_COS_ZENITH;
    float r = 0.0f;
    int step;
    for (step = 0; step < REFRACTION_TRUE_ZENITH_NEWTON_STEPS; ++step) {
        const float cr = cosf(r), sr = sinf(r);
        float c = cos_zt * cr + sin_zt * sr; /* cos(z_t - r) */
        const float s = sin_zt * cr - cos_zt * sr; /* sin(z_t - r) */
        float tz, g, dg;
        c = c > min_cos ? c : min_cos;
        tz = s / c;
        g = r - (a + b * tz * tz) * tz; /* f(r) = r - R(z_t - r) = 0 defines the refraction r */
        dg = 1.0f + (a + 3.0f * b * tz * tz) / (c * c);
        r = r - g / dg;
    }
    return r;
}

void refraction_rotate_in_vertical(const float r[3], float sin_z, const float tangential[3], float angle_rad,
                                   float angle_over_sin_z_at_zenith, float out[3])
{
    const float ratio = sin_z > 1e-12f ? sinf(angle_rad) / sin_z : angle_over_sin_z_at_zenith;
    const float ca = cosf(angle_rad);
    int c;
    for (c = 0; c < 3; ++c) {
        out[c] = ca * r[c] + ratio * tangential[c];
    }
}

void refraction_refract_toward_zenith(const float (*r)[3], size_t n, const float zenith[3], double a_rad,
                                      double b_rad, float (*out)[3])
{
    const float min_cos = (float)REFRACTION_MIN_COS_ZENITH;
    size_t i;
    for (i = 0u; i < n; ++i) {
        float cz, sz, t[3], refr, limit;
        refraction_zenith_geometry(&r[i], 1u, zenith, &cz, &sz, &t);
        refr = refraction_from_true_zenith(cz, sz, a_rad, b_rad);
        limit = (float)a_rad / (cz > min_cos ? cz : min_cos);
        refraction_rotate_in_vertical(r[i], sz, t, refr, limit, out[i]);
    }
}

/* ------------------------------------------------------------------------------------------------- fixed */

#define RR fixedpoint_rshift_round
#define DR fixedpoint_div_round

void refraction_cos_sin_q30(int64_t r_q36, int64_t *cos_q30, int64_t *sin_q30)
{
    const int q = FIXEDPOINT_Q;
    const int64_t r = RR(r_q36, REFRACTION_R_FRAC_BITS - q); /* Q30, |r| < 2^26.1 */
    const int64_t r2 = RR(r * r, q);
    const int64_t r4 = RR(r2 * r2, q);
    *cos_q30 = ((int64_t)1 << q) - RR(r2, 1) + DR(r4, 24);
    *sin_q30 = r - DR(RR(r * r2, q), 6);
}

int64_t refraction_from_true_zenith_q36(int64_t cos_q30, int64_t sin_q30, int64_t a_q56, int64_t b_q56)
{
    const int q = FIXEDPOINT_Q;
    const int64_t min_cos = 53687091; /* round(MIN_COS_ZENITH 2^30) */
    int64_t r = 0;
    int step;
    for (step = 0; step < REFRACTION_TRUE_ZENITH_NEWTON_STEPS; ++step) {
        int64_t cr, sr, c, s, tz, tz2, btz2, k, f, g, c2, dg;
        refraction_cos_sin_q30(r, &cr, &sr);
        c = RR(cos_q30 * cr + sin_q30 * sr, q); /* cos(z_t - R) */
        c = c > min_cos ? c : min_cos;
        s = RR(sin_q30 * cr - cos_q30 * sr, q); /* sin(z_t - R) */
        tz = DR(s * ((int64_t)1 << REFRACTION_TAN_FRAC_BITS), c); /* tan, Q24 */
        tz2 = RR(tz * tz, 2 * REFRACTION_TAN_FRAC_BITS - REFRACTION_TAN2_FRAC_BITS); /* Q16 */
        btz2 = RR(b_q56 * tz2, REFRACTION_TAN2_FRAC_BITS); /* B tan^2, Q56 */
        k = a_q56 + btz2;
        f = RR(RR(k, REFRACTION_COEF_FRAC_BITS - 40) * tz, 40 + REFRACTION_TAN_FRAC_BITS - REFRACTION_R_FRAC_BITS);
        g = r - f;
        c2 = RR(c * c, q);
        dg = ((int64_t)1 << q) + DR((a_q56 + 3 * btz2) * ((int64_t)1 << (2 * q - REFRACTION_COEF_FRAC_BITS)), c2);
        r = r - DR(g * ((int64_t)1 << q), dg);
    }
    return r;
}

void refraction_topocentric_observed_q30(const int64_t (*r_q30)[3], size_t n, const int64_t zenith_q30[3],
                                         const int64_t beta_q48[3], int with_refraction, int64_t a_q56,
                                         int64_t b_q56, int64_t (*out_q30)[3])
{
    const int q = FIXEDPOINT_Q, shift = REFRACTION_BETA_FRAC_BITS - FIXEDPOINT_Q;
    size_t i;
    int c;
    for (i = 0u; i < n; ++i) {
        const int64_t *r = r_q30[i];
        const int64_t rb = RR(r[0] * beta_q48[0] + r[1] * beta_q48[1] + r[2] * beta_q48[2], q); /* Q48 */
        int64_t topo[3], t[3], cz, sz, refr, cr, sr, ratio;
        for (c = 0; c < 3; ++c) {
            topo[c] = RR(r[c] * ((int64_t)1 << shift) + beta_q48[c] - RR(rb * r[c], q), shift);
        }
        if (!with_refraction) {
            for (c = 0; c < 3; ++c) {
                out_q30[i][c] = topo[c];
            }
            continue;
        }
        cz = RR(topo[0] * zenith_q30[0] + topo[1] * zenith_q30[1] + topo[2] * zenith_q30[2], q);
        for (c = 0; c < 3; ++c) {
            t[c] = zenith_q30[c] - RR(cz * topo[c], q); /* |t| = sin z */
        }
        sz = fixedpoint_isqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]);
        refr = refraction_from_true_zenith_q36(cz, sz, a_q56, b_q56);
        refraction_cos_sin_q30(refr, &cr, &sr);
        ratio = sz > 0 ? DR(sr * ((int64_t)1 << q), sz) : 0; /* sin R / sin z (t = 0 where sin z = 0) */
        for (c = 0; c < 3; ++c) {
            out_q30[i][c] = RR(cr * topo[c] + ratio * t[c], q);
        }
    }
}
