/* earth.c: onboard/earth.py's true_of_date_matrix in float32 (see earth.h). Constants are the model's, converted
 * from double to float32 where the model casts them. */
#include "earth.h"

#include <math.h>

#define EARTH_PI 3.14159265358979323846
#define ARCSEC_TO_RAD (EARTH_PI / 648000.0)
#define EPS0_AS 84381.406

static const double fw_gamma_as[6] = {-0.052928, 10.556378, 0.4932044, -0.00031238, -0.000002788, 0.0000000260};
static const double fw_psi_as[6] = {-0.041775, 5038.481484, 1.5584175, -0.00018522, -0.000026452, -0.0000000148};
static const double fw_phi_minus_eps0_as[6] = {0.006819, -46.811016, 0.0511268, 0.00053289, -0.000000440,
                                               -0.0000000176};
static const double eps_a_minus_eps0_as[6] = {0.0, -46.836769, -0.0001831, 0.00200340, -0.000000576, -0.0000000434};
/* Delaunay arguments [arcsec]: constant and rate per Julian century (Simon et al. 1994). */
static const double delaunay_as[5][2] = {
    {485868.249036, 1717915923.2178}, {1287104.79305, 129596581.0481}, {335779.526232, 1739527262.8478},
    {1072260.70369, 1602961601.2090}, {450160.398036, -6962890.5431},
};
/* IAU 2000B, 30 largest terms: multipliers of l l' F D Omega; dpsi sin, t sin, cos; deps cos, t cos, sin [0.1 uas]. */
static const int32_t nutation_terms[EARTH_NUTATION_TERMS][11] = {
    {0, 0, 0, 0, 1, -172064161, -174666, 33386, 92052331, 9086, 15377},
    {0, 0, 2, -2, 2, -13170906, -1675, -13696, 5730336, -3015, -4587},
    {0, 0, 2, 0, 2, -2276413, -234, 2796, 978459, -485, 1374},
    {0, 0, 0, 0, 2, 2074554, 207, -698, -897492, 470, -291},
    {0, 1, 0, 0, 0, 1475877, -3633, 11817, 73871, -184, -1924},
    {0, 1, 2, -2, 2, -516821, 1226, -524, 224386, -677, -174},
    {1, 0, 0, 0, 0, 711159, 73, -872, -6750, 0, 358},
    {0, 0, 2, 0, 1, -387298, -367, 380, 200728, 18, 318},
    {1, 0, 2, 0, 2, -301461, -36, 816, 129025, -63, 367},
    {0, -1, 2, -2, 2, 215829, -494, 111, -95929, 299, 132},
    {0, 0, 2, -2, 1, 128227, 137, 181, -68982, -9, 39},
    {-1, 0, 2, 0, 2, 123457, 11, 19, -53311, 32, -4},
    {-1, 0, 0, 2, 0, 156994, 10, -168, -1235, 0, 82},
    {1, 0, 0, 0, 1, 63110, 63, 27, -33228, 0, -9},
    {-1, 0, 0, 0, 1, -57976, -63, -189, 31429, 0, -75},
    {-1, 0, 2, 2, 2, -59641, -11, 149, 25543, -11, 66},
    {1, 0, 2, 0, 1, -51613, -42, 129, 26366, 0, 78},
    {-2, 0, 2, 0, 1, 45893, 50, 31, -24236, -10, 20},
    {0, 0, 0, 2, 0, 63384, 11, -150, -1220, 0, 29},
    {0, 0, 2, 2, 2, -38571, -1, 158, 16452, -11, 68},
    {0, -2, 2, -2, 2, 32481, 0, 0, -13870, 0, 0},
    {-2, 0, 0, 2, 0, -47722, 0, -18, 477, 0, -25},
    {2, 0, 2, 0, 2, -31046, -1, 131, 13238, -11, 59},
    {1, 0, 2, -2, 2, 28593, 0, -1, -12338, 10, -3},
    {-1, 0, 2, 0, 1, 20441, 21, 10, -10758, 0, -3},
    {2, 0, 0, 0, 0, 29243, 0, -74, -609, 0, 13},
    {0, 0, 2, 0, 0, 25887, 0, -66, -550, 0, 11},
    {0, 1, 0, 0, 1, -14053, -25, 79, 8551, -2, -45},
    {-1, 0, 0, 2, 1, 15164, 10, 11, -8001, 0, -1},
    {0, 2, 2, -2, 2, -15794, 72, -16, 6850, -42, -5},
};
/* IAU 2000B fixed offsets in lieu of the planetary terms (dpsi, deps) [arcsec]. */
static const double nutation_planetary_offset_as[2] = {-0.000135, 0.000388};

void earth_rot_x(float angle_rad, float m[3][3])
{
    const float c = cosf(angle_rad), s = sinf(angle_rad);
    m[0][0] = 1.0f, m[0][1] = 0.0f, m[0][2] = 0.0f;
    m[1][0] = 0.0f, m[1][1] = c, m[1][2] = s;
    m[2][0] = 0.0f, m[2][1] = -s, m[2][2] = c;
}

void earth_rot_y(float angle_rad, float m[3][3])
{
    const float c = cosf(angle_rad), s = sinf(angle_rad);
    m[0][0] = c, m[0][1] = 0.0f, m[0][2] = -s;
    m[1][0] = 0.0f, m[1][1] = 1.0f, m[1][2] = 0.0f;
    m[2][0] = s, m[2][1] = 0.0f, m[2][2] = c;
}

void earth_rot_z(float angle_rad, float m[3][3])
{
    const float c = cosf(angle_rad), s = sinf(angle_rad);
    m[0][0] = c, m[0][1] = s, m[0][2] = 0.0f;
    m[1][0] = -s, m[1][1] = c, m[1][2] = 0.0f;
    m[2][0] = 0.0f, m[2][1] = 0.0f, m[2][2] = 1.0f;
}

/* Horner evaluation of sum c_k t^k in float32 (onboard.earth._poly: acc = t * 0 + c5, then acc * t + c_k). */
static float poly(const double c[6], float t)
{
    float acc = t * 0.0f + (float)c[5];
    int k;
    for (k = 4; k >= 0; --k) {
        acc = acc * t + (float)c[k];
    }
    return acc;
}

void earth_precession_offsets(float t_c, float out[4])
{
    const float k = (float)ARCSEC_TO_RAD;
    out[0] = poly(fw_gamma_as, t_c) * k;
    out[1] = poly(fw_phi_minus_eps0_as, t_c) * k;
    out[2] = poly(fw_psi_as, t_c) * k;
    out[3] = poly(eps_a_minus_eps0_as, t_c) * k;
}

/* numpy's floating modulo for a positive divisor: fmod, shifted into [0, b). */
static float mod_positive(float a, float b)
{
    float m = fmodf(a, b);
    if (m != 0.0f && m < 0.0f) {
        m += b;
    }
    return m;
}

void earth_delaunay_arguments(float t_c, float args[5])
{
    int i;
    for (i = 0; i < 5; ++i) {
        const float x = (float)delaunay_as[i][0] + (float)delaunay_as[i][1] * t_c;
        args[i] = mod_positive(x, 1296000.0f) * (float)ARCSEC_TO_RAD;
    }
}

void earth_nutation(float t_c, float *dpsi, float *deps)
{
    float args[5], sum_psi = 0.0f, sum_eps = 0.0f;
    const float k = (float)(1e-7 * ARCSEC_TO_RAD);
    int i, j;
    earth_delaunay_arguments(t_c, args);
    for (i = 0; i < EARTH_NUTATION_TERMS; ++i) {
        const int32_t *row = nutation_terms[i];
        float phase = 0.0f, s, c;
        for (j = 0; j < 5; ++j) {
            phase += args[j] * (float)row[j];
        }
        s = sinf(phase);
        c = cosf(phase);
        sum_psi += ((float)row[5] + (float)row[6] * t_c) * s + (float)row[7] * c;
        sum_eps += ((float)row[8] + (float)row[9] * t_c) * c + (float)row[10] * s;
    }
    *dpsi = sum_psi * k + (float)(nutation_planetary_offset_as[0] * ARCSEC_TO_RAD);
    *deps = sum_eps * k + (float)(nutation_planetary_offset_as[1] * ARCSEC_TO_RAD);
}

static void matmul3(float a[3][3], float b[3][3], float out[3][3])
{
    float t[3][3];
    int i, j;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            t[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            out[i][j] = t[i][j];
        }
    }
}

void earth_true_of_date_matrix(timescale_time_t t_tt, float npb[3][3])
{
    /* R1(-(eps_A - eps_0 + deps)) [R1(-eps_0) R3(-(psi_bar + dpsi)) R1(eps_0)] R1(phi_bar - eps_0) R3(gamma_bar):
     * conjugating by the same rounded eps_0 keeps float32's rounding of the 84381" obliquity out of the result */
    const float t_c = timescale_julian_centuries(t_tt);
    float off[4], dpsi, deps, eps0[3][3], eps0_t[3][3], m[3][3], inner[3][3];
    int i, j;
    earth_precession_offsets(t_c, off);
    earth_nutation(t_c, &dpsi, &deps);
    earth_rot_x((float)(EPS0_AS * ARCSEC_TO_RAD), eps0);
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) {
            eps0_t[i][j] = eps0[j][i];
        }
    }
    earth_rot_z(-(off[2] + dpsi), m);
    matmul3(eps0_t, m, inner);
    matmul3(inner, eps0, inner);
    earth_rot_x(-(off[3] + deps), npb);
    matmul3(npb, inner, npb);
    earth_rot_x(off[1], m);
    matmul3(npb, m, npb);
    earth_rot_z(off[0], m);
    matmul3(npb, m, npb);
}
