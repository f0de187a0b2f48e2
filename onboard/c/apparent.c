/* apparent.c: onboard/apparent.py's per-star apparent place in integers, and the aberration change in float32. */
#include "apparent.h"

#include <math.h>

#include "earth.h"
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

/* ------------------------------------------------------------------------------------------------- float32 */

#define APPARENT_PI 3.14159265358979323846
#define APPARENT_ARCSEC_TO_RAD (APPARENT_PI / 648000.0)
#define APPARENT_SPEED_OF_LIGHT_M_S 299792458.0
#define APPARENT_ASTRONOMICAL_UNIT_M 149597870700.0
#define APPARENT_SUN_DEFLECTION_RAD 1.97412574336e-8
/* Kepler's equation: Newton iterations from E = M (a fixed count keeps the cost bounded). */
#define APPARENT_KEPLER_ITERATIONS 4

/* Mean Keplerian elements (Standish, JPL Table 1, 1800-2050), J2000 ecliptic: a [AU], e, I, L, varpi, Omega [deg],
 * each with its rate per Julian century. */
static const double elements_emb[6][2] = {{1.00000261, 0.00000562},   {0.01671123, -0.00004392},
                                          {-0.00001531, -0.01294668}, {100.46457166, 35999.37244981},
                                          {102.93768193, 0.32327364}, {0.0, 0.0}};
static const double elements_jupiter[6][2] = {{5.20288700, -0.00011607},  {0.04838624, -0.00013253},
                                              {1.30439695, -0.00183714},  {34.39644051, 3034.74612775},
                                              {14.72847983, 0.21252668},  {100.47390909, 0.20469106}};
static const double elements_saturn[6][2] = {{9.53667594, -0.00125060},  {0.05386179, -0.00050991},
                                             {2.48599187, 0.00193609},   {49.95424423, 1222.49362201},
                                             {92.59887831, -0.41897216}, {113.66242448, -0.28867794}};

static float mod_positive(float a, float b)
{
    float m = fmodf(a, b);
    if (m != 0.0f && m < 0.0f) {
        m += b;
    }
    return m;
}

/* Heliocentric position [AU] and velocity [AU/day] on a Keplerian orbit, J2000 ecliptic axes. */
static void kepler_state(const double el[6][2], float t, float pos[3], float vel[3])
{
    const float deg = (float)(APPARENT_PI / 180.0);
    const float a = (float)el[0][0] + (float)el[0][1] * t;
    const float e = (float)el[1][0] + (float)el[1][1] * t;
    const float inc = ((float)el[2][0] + (float)el[2][1] * t) * deg;
    const float big_l = mod_positive((float)el[3][0] + (float)el[3][1] * t, 360.0f) * deg;
    const float varpi = ((float)el[4][0] + (float)el[4][1] * t) * deg;
    const float node = ((float)el[5][0] + (float)el[5][1] * t) * deg;
    const float mean_motion = (float)el[3][1] * deg / (float)TIMESCALE_DAYS_PER_JULIAN_CENTURY; /* rad/day */
    const float m = big_l - varpi;
    float ecc = m, ce, se, root, x, y, edot, vx, vy, argp, cw, sw, co, so, ci, si, p[3], q[3];
    int i;
    for (i = 0; i < APPARENT_KEPLER_ITERATIONS; ++i) {
        ecc = ecc - (ecc - e * sinf(ecc) - m) / (1.0f - e * cosf(ecc));
    }
    ce = cosf(ecc);
    se = sinf(ecc);
    root = sqrtf(1.0f - e * e);
    x = a * (ce - e);
    y = a * root * se;
    edot = mean_motion / (1.0f - e * ce);
    vx = -a * se * edot;
    vy = a * root * ce * edot;
    argp = varpi - node;
    cw = cosf(argp), sw = sinf(argp), co = cosf(node), so = sinf(node), ci = cosf(inc), si = sinf(inc);
    /* orbital plane -> ecliptic: R3(-node) R1(-inc) R3(-argp) */
    p[0] = co * cw - so * sw * ci;
    p[1] = so * cw + co * sw * ci;
    p[2] = sw * si;
    q[0] = -co * sw - so * cw * ci;
    q[1] = -so * sw + co * cw * ci;
    q[2] = cw * si;
    for (i = 0; i < 3; ++i) {
        pos[i] = x * p[i] + y * q[i];
        vel[i] = vx * p[i] + vy * q[i];
    }
}

/* J2000 ecliptic -> J2000 equatorial (GCRS axes). */
static void ecliptic_to_equatorial(const float v[3], float out[3])
{
    const double eps0 = 84381.406 * APPARENT_ARCSEC_TO_RAD;
    const float c = (float)cos(eps0), s = (float)sin(eps0);
    const float x = v[0], y = v[1], z = v[2];
    out[0] = x;
    out[1] = c * y - s * z;
    out[2] = s * y + c * z;
}

void apparent_earth_barycentric_state(timescale_time_t t_tt, float earth_p[3], float earth_v[3], float earth_h[3])
{
    const double moon_fraction = 1.0 / 82.30057, moon_distance_au = 384400e3 / APPARENT_ASTRONOMICAL_UNIT_M;
    const double ratios[2] = {1.0 / 1047.3486, 1.0 / 3497.898};
    const float t_c = timescale_days_since_j2000(t_tt) / (float)TIMESCALE_DAYS_PER_JULIAN_CENTURY;
    const float moon_lon = mod_positive((float)218.3164477 + (float)481267.88123421 * t_c, 360.0f) *
                           (float)(APPARENT_PI / 180.0);
    const float moon_rate = (float)(481267.88123421 * APPARENT_PI / 180.0 / TIMESCALE_DAYS_PER_JULIAN_CENTURY);
    const float k = (float)(moon_fraction * moon_distance_au);
    float emb_p[3], emb_v[3], off_p[3], off_v[3], helio_p[3], helio_v[3], sun_p[3] = {0.0f, 0.0f, 0.0f};
    float sun_v[3] = {0.0f, 0.0f, 0.0f}, pp[3], pv[3], sum_p[3], sum_v[3];
    int i, planet;
    kepler_state(elements_emb, t_c, emb_p, emb_v);
    off_p[0] = -k * cosf(moon_lon);
    off_p[1] = -k * sinf(moon_lon);
    off_p[2] = -k * 0.0f;
    off_v[0] = -k * moon_rate * -sinf(moon_lon);
    off_v[1] = -k * moon_rate * cosf(moon_lon);
    off_v[2] = -k * moon_rate * 0.0f;
    for (i = 0; i < 3; ++i) {
        helio_p[i] = emb_p[i] + off_p[i];
        helio_v[i] = emb_v[i] + off_v[i];
    }
    for (planet = 0; planet < 2; ++planet) {
        kepler_state(planet == 0 ? elements_jupiter : elements_saturn, t_c, pp, pv);
        for (i = 0; i < 3; ++i) {
            sun_p[i] = sun_p[i] - (float)ratios[planet] * pp[i];
            sun_v[i] = sun_v[i] - (float)ratios[planet] * pv[i];
        }
    }
    for (i = 0; i < 3; ++i) {
        sum_p[i] = helio_p[i] + sun_p[i];
        sum_v[i] = helio_v[i] + sun_v[i];
    }
    ecliptic_to_equatorial(sum_p, earth_p);
    ecliptic_to_equatorial(sum_v, earth_v);
    ecliptic_to_equatorial(helio_p, earth_h);
}

static void normalise3(const float v[3], float out[3])
{
    const float norm = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    int c;
    for (c = 0; c < 3; ++c) {
        out[c] = v[c] / norm;
    }
}

void apparent_place_vectors(const float (*r0)[3], const float (*pm_rad_yr)[3], const float *parallax_mas, size_t n,
                            double epoch_jyear, timescale_time_t t_tt, float (*out)[3])
{
    const float au_light_time_day = (float)(APPARENT_ASTRONOMICAL_UNIT_M / APPARENT_SPEED_OF_LIGHT_M_S / 86400.0);
    float earth_p[3], earth_v[3], earth_h[3], tod[3][3], v_c[3], e[3], dist, k, years;
    size_t i;
    int c;
    apparent_earth_barycentric_state(t_tt, earth_p, earth_v, earth_h);
    earth_true_of_date_matrix(t_tt, tod);
    years = timescale_days_since_j2000(t_tt) / (float)TIMESCALE_DAYS_PER_JULIAN_YEAR + (float)(2000.0 - epoch_jyear);
    dist = sqrtf(earth_h[0] * earth_h[0] + earth_h[1] * earth_h[1] + earth_h[2] * earth_h[2]);
    for (c = 0; c < 3; ++c) {
        e[c] = earth_h[c] / dist;
        v_c[c] = earth_v[c] * au_light_time_day;
    }
    k = (float)APPARENT_SUN_DEFLECTION_RAD / dist;
    for (i = 0u; i < n; ++i) {
        const float plx = parallax_mas[i] * (float)(1e-3 * APPARENT_ARCSEC_TO_RAD);
        float change[3], p[3], pe, denom, kd, ab[3], w[3];
        /* space motion (pmpx without the Roemer term), then deflection at r0 + change, then aberration */
        for (c = 0; c < 3; ++c) {
            change[c] = years * pm_rad_yr[i][c] - plx * earth_p[c];
            p[c] = r0[i][c] + change[c];
        }
        pe = p[0] * e[0] + p[1] * e[1] + p[2] * e[2];
        denom = 1.0f + pe > 1e-6f ? 1.0f + pe : 1e-6f; /* a star behind the Sun */
        kd = k / denom;
        for (c = 0; c < 3; ++c) {
            change[c] = change[c] + kd * (e[c] - pe * p[c]);
            w[c] = r0[i][c] + change[c];
        }
        normalise3(w, p);
        apparent_aberration_change(p, v_c, ab);
        for (c = 0; c < 3; ++c) {
            change[c] = change[c] + ab[c];
            w[c] = r0[i][c] + change[c];
        }
        normalise3(w, p);
        for (c = 0; c < 3; ++c) {
            out[i][c] = p[0] * tod[c][0] + p[1] * tod[c][1] + p[2] * tod[c][2];
        }
    }
}
