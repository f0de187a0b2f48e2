/* fixedpoint.c: onboard/fixedpoint.py in integers (see fixedpoint.h for the formats and why nothing overflows). */
#include "fixedpoint.h"

#include <math.h>

const int64_t fixedpoint_rsqrt_table_q30[FIXEDPOINT_RSQRT_TABLE_SIZE] = {
    INT64_C(2083365155), INT64_C(1970666148), INT64_C(1874477403), INT64_C(1791125178), INT64_C(1717986918),
    INT64_C(1653133683), INT64_C(1595110808), INT64_C(1542797796), INT64_C(1495315678), INT64_C(1451963953),
    INT64_C(1412176547), INT64_C(1375490367), INT64_C(1341522399), INT64_C(1309952744), INT64_C(1280511844),
    INT64_C(1252970736), INT64_C(1227133513), INT64_C(1202831433), INT64_C(1179918259), INT64_C(1158266544),
    INT64_C(1137764631), INT64_C(1118314229), INT64_C(1099828423), INT64_C(1082230033), INT64_C(1065450257),
};

/* floor(t / 2^n) without the implementation-defined right shift of a negative value. */
static int64_t floor_shift(int64_t t, int n)
{
    if (t >= 0) {
        return t >> n;
    }
    return -(int64_t)((uint64_t)(-(t + 1)) >> n) - 1;
}

int64_t fixedpoint_rshift_round(int64_t a, int n)
{
    return floor_shift(a + ((int64_t)1 << (n - 1)), n);
}

int64_t fixedpoint_div_round(int64_t num, int64_t den)
{
    const int64_t t = num + (den >> 1);
    int64_t q = t / den;
    if (t % den != 0 && t < 0) {
        q -= 1; /* C truncates toward zero; the model floors */
    }
    return q;
}

int32_t fixedpoint_bit_length(int64_t x)
{
    static const int steps[6] = {32, 16, 8, 4, 2, 1};
    int32_t n = 0;
    int i;
    for (i = 0; i < 6; ++i) {
        if ((x >> steps[i]) > 0) {
            n += steps[i];
            x >>= steps[i];
        }
    }
    return n + (x > 0 ? 1 : 0);
}

int64_t fixedpoint_isqrt(int64_t n)
{
    int64_t x;
    int i;
    if (n <= 0) {
        return 0;
    }
    x = (int64_t)1 << ((fixedpoint_bit_length(n) + 1) >> 1);
    for (i = 0; i < FIXEDPOINT_ISQRT_ITERATIONS; ++i) {
        int64_t next = (x + n / x) >> 1; /* both positive: >> is a floor */
        if (next < 1) {
            next = 1;
        }
        if (next < x) {
            x = next;
        }
    }
    return x;
}

int64_t fixedpoint_rsqrt_q30(int64_t n2, int32_t *k)
{
    const int q = FIXEDPOINT_Q;
    const int32_t length = fixedpoint_bit_length(n2); /* 51..62 */
    int32_t sh = length - q - 1;
    int64_t a, y;
    int i;
    sh = sh + ((sh + 1) & 1); /* odd: 31 + sh even */
    a = fixedpoint_rshift_round(n2, (int)sh); /* in [2^29, 2^31] */
    y = fixedpoint_rsqrt_table_q30[(a >> 26) - FIXEDPOINT_RSQRT_TABLE_FIRST];
    for (i = 0; i < FIXEDPOINT_RSQRT_ITERATIONS; ++i) {
        const int64_t t1 = fixedpoint_rshift_round(a * y, q + 1);
        const int64_t t2 = fixedpoint_rshift_round(t1 * y, q);
        y = fixedpoint_rshift_round(y * (3 * ((int64_t)1 << q) - t2), q + 1);
    }
    *k = (q + 1 + sh) >> 1;
    return y;
}

int32_t fixedpoint_detector_shift(int32_t width_px, int32_t height_px)
{
    const int32_t side = width_px > height_px ? width_px : height_px;
    const int32_t s = fixedpoint_bit_length((int64_t)side - 1);
    return s > 1 ? s : 1;
}

/* Round to the nearest integer, ties to even (Python's round()), of a double known to fit an int64. */
static int64_t round_half_even(double x)
{
    const double fl = floor(x);
    const double diff = x - fl; /* exact */
    int64_t r = (int64_t)fl;
    if (diff > 0.5 || (diff == 0.5 && (r % 2) != 0)) {
        r += 1;
    }
    return r;
}

/* value -> (m, e) with value ~= m 2^-e, 2^27 <= |m| <= 2^28 (round half even), e <= 62 (exact for a float32). */
static void block_float(double value, int64_t *m, int32_t *e)
{
    int exp2;
    int32_t ee;
    if (value == 0.0) {
        *m = 0;
        *e = FIXEDPOINT_COEF_MAX_EXP;
        return;
    }
    (void)frexp(value, &exp2);
    ee = FIXEDPOINT_COEF_BITS - exp2;
    if (ee > FIXEDPOINT_COEF_MAX_EXP) {
        ee = FIXEDPOINT_COEF_MAX_EXP;
    }
    *m = round_half_even(ldexp(value, ee));
    *e = ee;
}

double fixedpoint_distortion_share(const fixedpoint_camera_t *cam)
{
    const int q = FIXEDPOINT_Q;
    const int s = (int)cam->s;
    const double scale_px = ldexp(1.0, s);
    double coef[7], corners_x[2], corners_y[2], rho2 = 0.0, rho, c_rad, c_tan, tan_a, tan_b;
    int i, j;
    for (i = 0; i < 7; ++i) {
        coef[i] = ldexp((double)cam->coef_m[i], -(int)cam->coef_e[i]);
    }
    corners_x[0] = -0.5 - ldexp((double)cam->x0_q, s - q);
    corners_x[1] = (double)cam->width_px - 0.5 - ldexp((double)cam->x0_q, s - q);
    corners_y[0] = -0.5 - ldexp((double)cam->y0_q, s - q);
    corners_y[1] = (double)cam->height_px - 0.5 - ldexp((double)cam->y0_q, s - q);
    for (i = 0; i < 2; ++i) {
        for (j = 0; j < 2; ++j) {
            const double r2 = corners_x[i] * corners_x[i] + corners_y[j] * corners_y[j];
            if (r2 > rho2) {
                rho2 = r2;
            }
        }
    }
    rho2 = rho2 / (scale_px * scale_px);
    rho = sqrt(rho2);
    c_rad = fabs(coef[0]) * rho2 + fabs(coef[1]) * (rho2 * rho2) + fabs(coef[2]) * (rho2 * rho2 * rho2);
    tan_a = 3.0 * fabs(coef[3]) + fabs(coef[4]) + fabs(coef[5]);
    tan_b = 3.0 * fabs(coef[4]) + fabs(coef[3]) + fabs(coef[6]);
    c_tan = rho * (tan_a > tan_b ? tan_a : tan_b);
    return c_rad + c_tan;
}

fixedpoint_status_t fixedpoint_camera(const float theta[CAMERA_N_PARAMS], int32_t width_px, int32_t height_px,
                                      fixedpoint_camera_t *cam)
{
    static const int powers[7] = {2, 4, 6, 1, 1, 1, 1};
    const int q = FIXEDPOINT_Q;
    double t[CAMERA_N_PARAMS], coef[7];
    double f_px, x0, y0, scale_px, cap;
    int32_t s, e_k;
    int i, exp2;
    s = fixedpoint_detector_shift(width_px, height_px);
    if (s > FIXEDPOINT_MAX_DETECTOR_SHIFT) {
        return FIXEDPOINT_ERR_DETECTOR_SIZE;
    }
    for (i = 0; i < CAMERA_N_PARAMS; ++i) {
        t[i] = (double)theta[i];
        if (!isfinite(t[i])) {
            return FIXEDPOINT_ERR_NOT_FINITE;
        }
    }
    f_px = t[0];
    x0 = t[1];
    y0 = t[2];
    if (!(-0.5 <= x0 && x0 <= (double)width_px - 0.5 && -0.5 <= y0 && y0 <= (double)height_px - 0.5)) {
        return FIXEDPOINT_ERR_PRINCIPAL_POINT;
    }
    scale_px = ldexp(1.0, (int)s);
    if (!(f_px >= scale_px / 8.0)) {
        return FIXEDPOINT_ERR_FOCAL;
    }
    if (!(f_px <= FIXEDPOINT_MAX_FOCAL_PX)) {
        return FIXEDPOINT_ERR_FOCAL_LONG;
    }
    cam->s = s;
    cam->width_px = width_px;
    cam->height_px = height_px;
    cam->x0_q = round_half_even(ldexp(x0, q - (int)s)); /* exact scaling by a power of two */
    cam->y0_q = round_half_even(ldexp(y0, q - (int)s));
    for (i = 0; i < 7; ++i) { /* k1 S^2, k2 S^4, k3 S^6, p S, s S */
        block_float(ldexp(t[3 + i], (int)s * powers[i]), &cam->coef_m[i], &e_k);
        cam->coef_e[i] = e_k;
        coef[i] = ldexp((double)cam->coef_m[i], -(int)e_k);
    }
    if (!(fixedpoint_distortion_share(cam) <= 1.0)) {
        return FIXEDPOINT_ERR_DISTORTION;
    }
    cap = f_px / scale_px > 4.0 ? f_px / scale_px : 4.0;
    {
        const double frac = frexp(cap, &exp2);
        cam->qw = q - (frac == 0.5 ? exp2 - 1 : exp2); /* 30 - ceil(log2 cap) */
    }
    cam->f_w = round_half_even(ldexp(f_px, (int)cam->qw - (int)s));
    cam->theta_q[0] = ldexp((double)cam->f_w, (int)s - (int)cam->qw);
    cam->theta_q[1] = ldexp((double)cam->x0_q, (int)s - q);
    cam->theta_q[2] = ldexp((double)cam->y0_q, (int)s - q);
    for (i = 0; i < 7; ++i) {
        cam->theta_q[3 + i] = ldexp(coef[i], -(int)s * powers[i]);
    }
    return FIXEDPOINT_OK;
}

int fixedpoint_on_detector(int64_t x_q10, int64_t y_q10, int32_t width_px, int32_t height_px)
{
    const int64_t half = (int64_t)1 << (FIXEDPOINT_CENTROID_FRAC_BITS - 1);
    const int64_t steps = (int64_t)1 << FIXEDPOINT_CENTROID_FRAC_BITS;
    return x_q10 >= -half && x_q10 <= (int64_t)width_px * steps - half && y_q10 >= -half &&
           y_q10 <= (int64_t)height_px * steps - half;
}

/* power (Q30, < 2^34) times coefficient k (|m| <= 2^28) -> Q30: the product stays below 2^62. */
static int64_t coef_term(int64_t power_q30, const fixedpoint_camera_t *cam, int k)
{
    return fixedpoint_rshift_round(power_q30 * cam->coef_m[k], (int)cam->coef_e[k]);
}

fixedpoint_status_t fixedpoint_ideal_offsets_q30(int64_t x_q10, int64_t y_q10, const fixedpoint_camera_t *cam,
                                                 int64_t *u_ideal_q30, int64_t *v_ideal_q30)
{
    const int q = FIXEDPOINT_Q;
    const int64_t one = (int64_t)1 << q;
    const int64_t grid = (int64_t)1 << (FIXEDPOINT_MAX_DETECTOR_SHIFT - cam->s); /* Q10 px -> Q(30 - s) px */
    const int64_t far = (int64_t)1 << 40; /* 2^30 px: x_q10 grid stays below 2^59 */
    int64_t u, v, uu, vv, uv, r2, r4, r6, radial, ru, rv, uv2, dx, dy;
    if (x_q10 > far || x_q10 < -far || y_q10 > far || y_q10 < -far) {
        return FIXEDPOINT_ERR_CENTROID; /* far off any detector: refuse before the products below */
    }
    u = x_q10 * grid - cam->x0_q;
    v = y_q10 * grid - cam->y0_q;
    if (u > one || u < -one || v > one || v < -one) {
        return FIXEDPOINT_ERR_CENTROID;
    }
    uu = fixedpoint_rshift_round(u * u, q);
    vv = fixedpoint_rshift_round(v * v, q);
    uv = fixedpoint_rshift_round(u * v, q);
    r2 = uu + vv;
    r4 = fixedpoint_rshift_round(r2 * r2, q);
    r6 = fixedpoint_rshift_round(fixedpoint_rshift_round(r4, 1) * r2, q - 1); /* halve r4 first: <= 2^62 */
    radial = coef_term(r2, cam, 0) + coef_term(r4, cam, 1) + coef_term(r6, cam, 2);
    ru = fixedpoint_rshift_round(u * radial, q);
    rv = fixedpoint_rshift_round(v * radial, q);
    uv2 = uv + uv;
    dx = ru + coef_term(3 * uu + vv, cam, 3) + coef_term(uv2, cam, 4) + coef_term(r2, cam, 5);
    dy = rv + coef_term(uu + 3 * vv, cam, 4) + coef_term(uv2, cam, 3) + coef_term(r2, cam, 6);
    *u_ideal_q30 = u - dx;
    *v_ideal_q30 = v - dy;
    return FIXEDPOINT_OK;
}

void fixedpoint_offsets_to_unit_q30(int64_t u_ideal_q30, int64_t v_ideal_q30, const fixedpoint_camera_t *cam,
                                    int64_t b_q30[3])
{
    const int down = FIXEDPOINT_Q - (int)cam->qw; /* >= 2 */
    const int64_t wu = fixedpoint_rshift_round(u_ideal_q30, down);
    const int64_t wv = fixedpoint_rshift_round(v_ideal_q30, down);
    const int64_t wf = cam->f_w;
    const int64_t n2 = wu * wu + wv * wv + wf * wf; /* in [2^50, 3 2^60) */
    int32_t k;
    const int64_t y = fixedpoint_rsqrt_q30(n2, &k);
    b_q30[0] = fixedpoint_rshift_round(wu * y, (int)k);
    b_q30[1] = fixedpoint_rshift_round(wv * y, (int)k);
    b_q30[2] = fixedpoint_rshift_round(wf * y, (int)k);
}

void fixedpoint_normalise_q30(const int64_t w[3], int64_t out_q30[3])
{
    const int64_t n2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    int32_t k;
    const int64_t y = fixedpoint_rsqrt_q30(n2, &k);
    int c;
    for (c = 0; c < 3; ++c) {
        out_q30[c] = fixedpoint_rshift_round(w[c] * y, (int)k);
    }
}

fixedpoint_status_t fixedpoint_pixels_to_unit_q30(int64_t x_q10, int64_t y_q10, const fixedpoint_camera_t *cam,
                                                  int64_t b_q30[3])
{
    int64_t u, v;
    const fixedpoint_status_t status = fixedpoint_ideal_offsets_q30(x_q10, y_q10, cam, &u, &v);
    if (status != FIXEDPOINT_OK) {
        return status;
    }
    fixedpoint_offsets_to_unit_q30(u, v, cam, b_q30);
    return FIXEDPOINT_OK;
}

void fixedpoint_difference_residuals_q61(const int64_t (*b_q30)[3], const int64_t (*r_q30)[3], const int32_t *pi,
                                         const int32_t *pj, size_t n_pairs, int64_t *e_q61)
{
    size_t p;
    int c;
    for (p = 0u; p < n_pairs; ++p) {
        int64_t sb = 0, sr = 0;
        for (c = 0; c < 3; ++c) {
            const int64_t db = b_q30[pi[p]][c] - b_q30[pj[p]][c];
            const int64_t dr = r_q30[pi[p]][c] - r_q30[pj[p]][c];
            sb += db * db; /* Q60, partial sums <= the total <= 4 2^60 (1 + 2^-28) */
            sr += dr * dr;
        }
        e_q61[p] = sb - sr;
    }
}

void fixedpoint_residuals_to_float(const int64_t *e_q61, size_t n, float *e)
{
    const float scale = 4.33680868994201773602981120347976684570312e-19f; /* 2^-61, exact */
    size_t p;
    for (p = 0u; p < n; ++p) {
        e[p] = (float)e_q61[p] * scale;
    }
}

int64_t fixedpoint_quantise_px(double value_px)
{
    const double clip = 1099511627776.0; /* 2^40 px: keeps the Q10 steps inside int64 */
    double v = value_px;
    if (isnan(v)) {
        return 0; /* not a centroid: defined here only so that no conversion is undefined (the caller refuses it) */
    }
    if (v > clip) {
        v = clip;
    } else if (v < -clip) {
        v = -clip;
    }
    return round_half_even(v * (double)((int64_t)1 << FIXEDPOINT_CENTROID_FRAC_BITS));
}

int64_t fixedpoint_quantise_unit_q30(double component)
{
    /* a unit vector's component is within [-1, 1]; anything beyond +-2 (or NaN) is not one and is clamped so that
     * the conversion to int64 stays defined (the Python model would produce an unspecified integer) */
    double v = isnan(component) ? 0.0 : component;
    v = v > 2.0 ? 2.0 : (v < -2.0 ? -2.0 : v);
    return round_half_even(ldexp(v, FIXEDPOINT_Q));
}
