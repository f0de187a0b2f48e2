/* apparent.c: onboard/apparent.py's per-star apparent place in integers, and the aberration change in float32. */
#include "apparent.h"

#include <math.h>

#include "fixedpoint.h"

#define RR fixedpoint_rshift_round

static int64_t dot3(const int64_t a[3], const int64_t b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

void apparent_place_vectors_q30(const int64_t (*r0_q30)[3], const int64_t (*pm_q46)[3], const int64_t *parallax_q48,
                                size_t n, const apparent_instant_t *inst, int64_t (*out_q30)[3])
{
    const int q = FIXEDPOINT_Q, up = APPARENT_CHANGE_FRAC_BITS - FIXEDPOINT_Q, vb = APPARENT_ABERRATION_BETA_FRAC_BITS;
    const int64_t up_scale = (int64_t)1 << up;
    const int64_t *e = inst->sun_to_earth_q30, *v = inst->beta_q44;
    size_t i;
    int c;
    for (i = 0u; i < n; ++i) {
        const int64_t *r0 = r0_q30[i];
        int64_t c1[3], c2[3], c3[3], w[3], p[3], pe, one_pe, qd, pv, v2, m;
        /* space motion: years pm - parallax E_b (Q48) */
        for (c = 0; c < 3; ++c) {
            c1[c] = RR(inst->years_q20 * pm_q46[i][c],
                       APPARENT_YEARS_FRAC_BITS + APPARENT_PM_FRAC_BITS - APPARENT_CHANGE_FRAC_BITS);
            c1[c] = c1[c] - RR(parallax_q48[i] * inst->earth_bary_q30[c], q);
        }
        /* light deflection at p = r0 + c1: k (e - (p.e) p) / (1 + p.e) (Q48) */
        for (c = 0; c < 3; ++c) {
            p[c] = RR(r0[c] * up_scale + c1[c], up);
        }
        pe = RR(dot3(p, e), q);
        one_pe = ((int64_t)1 << q) + pe;
        one_pe = one_pe > APPARENT_MIN_ONE_PLUS_PE_Q30 ? one_pe : APPARENT_MIN_ONE_PLUS_PE_Q30;
        qd = fixedpoint_div_round(
            inst->deflection_k_q70 * ((int64_t)1 << (APPARENT_CHANGE_FRAC_BITS + q - APPARENT_DEFLECTION_K_FRAC_BITS)),
            one_pe);
        for (c = 0; c < 3; ++c) {
            c2[c] = c1[c] + RR(qd * (e[c] - RR(pe * p[c], q)), q);
        }
        /* aberration at the normalised direction, to second order (Q44) */
        for (c = 0; c < 3; ++c) {
            w[c] = RR(r0[c] * up_scale + c2[c], up);
        }
        fixedpoint_normalise_q30(w, p);
        pv = RR(dot3(p, v), q);
        v2 = RR(dot3(v, v), vb);
        m = pv - RR(pv * pv, vb) + RR(v2, 1);
        for (c = 0; c < 3; ++c) {
            const int64_t ab = v[c] - RR(pv * v[c], vb + 1) - RR(m * p[c], q);
            c3[c] = c2[c] + ab * ((int64_t)1 << (APPARENT_CHANGE_FRAC_BITS - vb));
        }
        /* normalise, then rotate to the true equator and equinox of date */
        for (c = 0; c < 3; ++c) {
            w[c] = RR(r0[c] * up_scale + c3[c], up);
        }
        fixedpoint_normalise_q30(w, p);
        for (c = 0; c < 3; ++c) {
            out_q30[i][c] = RR(dot3(p, inst->tod_q30[c]), q);
        }
    }
}

void apparent_aberration_change(const float p[3], const float velocity_c[3], float change[3])
{
    const float *v = velocity_c;
    const float v2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    const float bm1 = sqrtf(1.0f - v2);
    const float pv = p[0] * v[0] + p[1] * v[1] + p[2] * v[2];
    const float w1 = 1.0f + pv / (1.0f + bm1);
    const float along = pv + v2 / (1.0f + bm1);
    int c;
    for (c = 0; c < 3; ++c) {
        change[c] = (w1 * v[c] - along * p[c]) / (1.0f + pv);
    }
}
