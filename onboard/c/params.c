/* params.c: onboard.params.validate_params / check_plausible (float32) and onboard.prior.validate_sigma for a staged
 * table (params.h). Every float32 expression is written in the reference's order, one operation at a time. */
#include "params.h"

#include <math.h>

#include "fixedpoint.h"

static const char *const DISTORTION_FIELDS[7] = {"distortion.k1", "distortion.k2", "distortion.k3", "distortion.p1",
                                                 "distortion.p2", "distortion.s1", "distortion.s2"};
/* onboard.prior.SIGMA_FILE_FIELDS */
static const char *const SIGMA_FIELDS[10] = {
    "sigma.focal_length_mm", "sigma.principal_point_px[0]", "sigma.principal_point_px[1]",
    "sigma.distortion.k1",   "sigma.distortion.k2",         "sigma.distortion.k3",
    "sigma.distortion.p1",   "sigma.distortion.p2",         "sigma.distortion.s1",
    "sigma.distortion.s2"};
static const char *const IMAGE_FIELDS[2] = {"image_size_px[0]", "image_size_px[1]"};
static const char *const PP_FIELDS[2] = {"principal_point_px[0]", "principal_point_px[1]"};

/* A parameter set as the sensor holds it: the camera model vector in float32 (slot 0 = F in px) and the file
 * values as doubles (the exact float32 values, as Python floats hold them). */
typedef struct {
    double f_mm;
    double pitch_um;
    double pp[2];
    double size[2]; /* whole numbers */
    float theta[10];
} camera_t;

params_limits_t params_default_limits(double design_focal_length_mm)
{
    params_limits_t l;
    l.has_limits = 1u;
    l.design_focal_length_mm = design_focal_length_mm;
    l.focal_tolerance = PARAMS_FOCAL_TOLERANCE;
    l.max_distortion_fraction = PARAMS_MAX_DISTORTION_FRACTION;
    l.design_name = "design value";
    l.fixed_point = 0u;
    return l;
}

static int refuse(pyformat_text_t *why, const char *field, const char *reason)
{
    pyformat_init(why);
    pyformat_str(why, field);
    pyformat_str(why, ": ");
    pyformat_str(why, reason);
    return 1;
}

static int is_whole(double v)
{
    if (!isfinite(v)) {
        return 0;
    }
    if (fabs(v) >= 4503599627370496.0) { /* 2^52: every double this large is a whole number */
        return 1;
    }
    return (double)(int64_t)v == v;
}

/* the 17 grid coordinates of a detector side of n px: np.linspace(-0.5, n - 0.5, 17) in float64, then float32 */
static void grid(double n, float out[PARAMS_GRID])
{
    const double start = -0.5;
    const double stop = n - 0.5;
    const double step = (stop - start) / (double)(PARAMS_GRID - 1);
    int k;
    for (k = 0; k < PARAMS_GRID; ++k) {
        double y = (double)k * step;
        y += start;
        out[k] = (float)y;
    }
    out[PARAMS_GRID - 1] = (float)stop;
}

/* onboard.camera.distortion_partials: (1 - dx_u) (1 - dy_v) - (-dx_v) (-dy_u), the Jacobian determinant */
static float mapping_determinant(float u, float v, const float *t)
{
    const float k1 = t[3], k2 = t[4], k3 = t[5], p1 = t[6], p2 = t[7], s1 = t[8], s2 = t[9];
    const float two = 2.0f, three = 3.0f;
    const float g1 = s1 + p1, g2 = s2 + p2, g3 = p1 + p1, g4 = p2 + p2;
    const float r2 = u * u + v * v;
    const float radial = r2 * (k1 + r2 * (k2 + r2 * k3));
    const float radial_d = k1 + r2 * (two * k2 + three * k3 * r2);
    const float dx_u = two * (g1 + g3) * u + g4 * v + radial + two * u * u * radial_d;
    const float dx_v = g4 * u + two * g1 * v + two * u * v * radial_d;
    const float dy_u = two * g2 * u + g3 * v + two * u * v * radial_d;
    const float dy_v = g3 * u + two * (g2 + g4) * v + radial + two * v * v * radial_d;
    const float j00 = 1.0f - dx_u, j01 = -dx_v, j10 = -dy_u, j11 = 1.0f - dy_v;
    return j00 * j11 - j01 * j10;
}

/* onboard.camera.distortion_px: |(dx, dy)| */
static float displacement(float u, float v, const float *t)
{
    const float k1 = t[3], k2 = t[4], k3 = t[5], p1 = t[6], p2 = t[7], s1 = t[8], s2 = t[9];
    const float g1 = s1 + p1, g2 = s2 + p2, g3 = p1 + p1, g4 = p2 + p2;
    const float r2 = u * u + v * v;
    const float radial = r2 * (k1 + r2 * (k2 + r2 * k3));
    const float dx = (g1 + g3) * u * u + g4 * u * v + g1 * v * v + u * radial;
    const float dy = g2 * u * u + g3 * u * v + (g2 + g4) * v * v + v * radial;
    return hypotf(dx, dy);
}

/* onboard.params.min_radial_slope in float32: the smallest slope and the radius where it occurs */
static void min_radial_slope(const float *t, double s_max_px2, float *p_min, float *r_at)
{
    const float k1 = t[3], k2 = t[4], k3 = t[5];
    const float one = 1.0f, two = 2.0f, three = 3.0f, four = 4.0f, five = 5.0f, seven = 7.0f, ten = 10.0f,
                c21 = 21.0f;
    const float s_max = (float)s_max_px2;
    float cand[4];
    float s[4];
    int n_cand = 0, n = 0, i, best = 0;
    float a, b, c;
    cand[n_cand++] = 0.0f;
    cand[n_cand++] = s_max;
    a = -c21 * k3;
    b = -ten * k2;
    c = -three * k1;
    if (a != 0.0f) {
        const float disc = b * b - four * a * c;
        if (disc >= 0.0f) {
            const float root = sqrtf(disc);
            cand[n_cand++] = (-b - root) / (two * a);
            cand[n_cand++] = (-b + root) / (two * a);
        }
    } else if (b != 0.0f) {
        cand[n_cand++] = -c / b;
    }
    for (i = 0; i < n_cand; ++i) {
        if (isfinite(cand[i]) && 0.0f <= cand[i] && cand[i] <= s_max) {
            s[n++] = cand[i];
        }
    }
    /* np.argmin: the first NaN if there is one, else the first smallest */
    for (i = 0; i < n; ++i) {
        const float slope = one - s[i] * (three * k1 + s[i] * (five * k2 + s[i] * (seven * k3)));
        const float kept = one - s[best] * (three * k1 + s[best] * (five * k2 + s[best] * (seven * k3)));
        if (isnan(kept)) {
            break;
        }
        if (isnan(slope) || slope < kept) {
            best = i;
        }
    }
    *p_min = one - s[best] * (three * k1 + s[best] * (five * k2 + s[best] * (seven * k3)));
    *r_at = sqrtf(s[best]);
}

/* The scalar checks of onboard.params.validate_params, in its order: every value finite; f > 0, p > 0; the image
 * size in 1..2^24; F = 1000 f / p finite; the principal point on the detector [-0.5, n - 0.5]. */
static int refuse_scalars(const camera_t *cam, pyformat_text_t *why)
{
    static const char *const names[4] = {"focal_length_mm", "pixel_pitch_um", "principal_point_px[0]",
                                         "principal_point_px[1]"};
    const double scalars[4] = {cam->f_mm, cam->pitch_um, cam->pp[0], cam->pp[1]};
    double focal_px;
    int i;
    for (i = 0; i < 4; ++i) {
        if (!isfinite(scalars[i])) {
            refuse(why, names[i], "must be finite, got ");
            pyformat_repr(why, scalars[i]);
            return 1;
        }
    }
    for (i = 0; i < 7; ++i) {
        if (!isfinite(cam->theta[3 + i])) {
            refuse(why, DISTORTION_FIELDS[i], "must be finite, got ");
            pyformat_repr(why, (double)cam->theta[3 + i]);
            return 1;
        }
    }
    if (cam->f_mm <= 0.0) {
        refuse(why, "focal_length_mm", "must be > 0, got ");
        pyformat_repr(why, cam->f_mm);
        return 1;
    }
    if (cam->pitch_um <= 0.0) {
        refuse(why, "pixel_pitch_um", "must be > 0, got ");
        pyformat_repr(why, cam->pitch_um);
        return 1;
    }
    for (i = 0; i < 2; ++i) {
        if (!(1.0 <= cam->size[i] && cam->size[i] <= PARAMS_MAX_IMAGE_SIDE_PX)) {
            refuse(why, IMAGE_FIELDS[i], "must be in 1..16777216, got ");
            pyformat_g(why, cam->size[i], 6u);
            return 1;
        }
    }
    focal_px = 1000.0 * cam->f_mm / cam->pitch_um;
    if (!isfinite(focal_px)) {
        refuse(why, "focal_length_mm", "the focal length in pixels 1000 f / p = ");
        pyformat_repr(why, focal_px);
        pyformat_str(why, " is not finite");
        return 1;
    }
    for (i = 0; i < 2; ++i) {
        if (!(-0.5 <= cam->pp[i] && cam->pp[i] <= cam->size[i] - 0.5)) {
            pyformat_init(why);
            pyformat_str(why, PP_FIELDS[i]);
            pyformat_str(why, ": ");
            pyformat_repr(why, cam->pp[i]);
            pyformat_str(why, " is off the detector [-0.5, ");
            pyformat_repr(why, cam->size[i] - 0.5);
            pyformat_str(why, "]");
            return 1;
        }
    }
    return 0;
}

/* onboard.params.farthest_corner_radius2_px2 (float64) */
static double farthest_corner_radius2_px2(const camera_t *cam)
{
    double a, b, du, dv;
    a = fabs(-0.5 - cam->pp[0]);
    b = fabs(cam->size[0] - 0.5 - cam->pp[0]);
    du = b > a ? b : a;
    a = fabs(-0.5 - cam->pp[1]);
    b = fabs(cam->size[1] - 0.5 - cam->pp[1]);
    dv = b > a ? b : a;
    return du * du + dv * dv;
}

/* onboard.params.min_mapping_determinant in float32: the smallest determinant over the 17 x 17 grid (NaN counts as
 * -inf) and the grid coordinates where it occurs (np.argmin's first smallest, row by row). */
static float min_mapping_determinant(const camera_t *cam, float *x_at, float *y_at)
{
    float xs[PARAMS_GRID], ys[PARAMS_GRID], det_min = 0.0f;
    int ix, iy, best_x = 0, best_y = 0;
    grid(cam->size[0], xs);
    grid(cam->size[1], ys);
    for (iy = 0; iy < PARAMS_GRID; ++iy) {
        for (ix = 0; ix < PARAMS_GRID; ++ix) {
            const float u = xs[ix] - cam->theta[1];
            const float v = ys[iy] - cam->theta[2];
            float det = mapping_determinant(u, v, cam->theta);
            if (isnan(det)) {
                det = -INFINITY;
            }
            if ((ix == 0 && iy == 0) || det < det_min) {
                det_min = det;
                best_x = ix;
                best_y = iy;
            }
        }
    }
    *x_at = xs[best_x];
    *y_at = ys[best_y];
    return det_min;
}

/* onboard.params.validate_params in float32: the scalars, the farthest corner's distance, then the distortion's
 * mapping one-to-one over the detector (the radial slope from 0 to the farthest corner, the Jacobian determinant on
 * the grid). */
static int validate_params(const camera_t *cam, pyformat_text_t *why)
{
    double s_max;
    float p_min, r_at, det_min, x_at, y_at;
    if (refuse_scalars(cam, why)) {
        return 1;
    }
    s_max = farthest_corner_radius2_px2(cam);
    if (!(s_max <= PARAMS_MAX_CORNER_RADIUS_PX * PARAMS_MAX_CORNER_RADIUS_PX)) {
        refuse(why, "image_size_px", "the farthest corner is ");
        pyformat_f0(why, sqrt(s_max));
        pyformat_str(why, " px from the principal point, beyond 262144 px (a float32 sensor's distortion Jacobian "
                          "r^7 would overflow)");
        return 1;
    }
    min_radial_slope(cam->theta, s_max, &p_min, &r_at);
    if (!(p_min > 0.0f)) {
        refuse(why, "distortion", "radial mapping is not one-to-one: d r'/d r = ");
        pyformat_g(why, (double)p_min, 3u);
        pyformat_str(why, " at radius ");
        pyformat_g(why, (double)r_at, 3u);
        pyformat_str(why, " px (the farthest corner is at ");
        pyformat_f0(why, sqrt(s_max));
        pyformat_str(why, " px)");
        return 1;
    }
    det_min = min_mapping_determinant(cam, &x_at, &y_at);
    if (!(det_min > 0.0f)) {
        refuse(why, "distortion", "mapping is not monotonic over the detector (Jacobian determinant ");
        pyformat_g(why, (double)det_min, 3u);
        pyformat_str(why, " at pixel (");
        pyformat_f0(why, (double)x_at);
        pyformat_str(why, ", ");
        pyformat_f0(why, (double)y_at);
        pyformat_str(why, "))");
        return 1;
    }
    return 0;
}

/* onboard.params.check_plausible's rule 4: fixedpoint_camera at the float32 model vector, the refusal worded as
 * onboard.fixedpoint.fixed_camera's FixedRangeError */
static int refuse_fixed(const camera_t *cam, pyformat_text_t *why)
{
    const int32_t w = (int32_t)cam->size[0], h = (int32_t)cam->size[1];
    fixedpoint_camera_t fc;
    const fixedpoint_status_t status = fixedpoint_camera(cam->theta, w, h, &fc);
    if (status == FIXEDPOINT_OK) {
        return 0;
    }
    refuse(why, "fixed point", "outside the sensor's range: ");
    switch (status) {
    case FIXEDPOINT_ERR_DETECTOR_SIZE:
        pyformat_str(why, "detector side ");
        pyformat_i64(why, w > h ? w : h);
        pyformat_str(why, " px exceeds the fixed-point range (2^20)");
        break;
    case FIXEDPOINT_ERR_PRINCIPAL_POINT:
        pyformat_str(why, "principal point (");
        pyformat_repr(why, (double)cam->theta[1]);
        pyformat_str(why, ", ");
        pyformat_repr(why, (double)cam->theta[2]);
        pyformat_str(why, ") px is off the detector");
        break;
    case FIXEDPOINT_ERR_FOCAL:
        pyformat_str(why, "focal length ");
        pyformat_g(why, (double)cam->theta[0], 6u);
        pyformat_str(why, " px is below S/8 = ");
        pyformat_f0(why, ldexp(1.0, (int)fixedpoint_detector_shift(w, h)) / 8.0);
        pyformat_str(why, " px (field too wide)");
        break;
    case FIXEDPOINT_ERR_FOCAL_LONG:
        pyformat_str(why, "focal length ");
        pyformat_g(why, (double)cam->theta[0], 6u);
        pyformat_str(why, " px is above 2^20 = 1048576 px (Q30 unit vectors coarser than the Q10 centroids)");
        break;
    case FIXEDPOINT_ERR_DISTORTION:
        pyformat_str(why, "distortion correction up to ");
        pyformat_f0(why, 100.0 * fixedpoint_distortion_share(&fc));
        pyformat_str(why, " % of the radius exceeds the fixed-point range (100 %)");
        break;
    default: /* FIXEDPOINT_ERR_NOT_FINITE (a centroid status cannot come from fixedpoint_camera) */
        pyformat_str(why, "parameters must be finite");
        break;
    }
    return 1;
}

static int check_plausible(const camera_t *cam, const params_limits_t *limits, pyformat_text_t *why)
{
    float xs[PARAMS_GRID], ys[PARAMS_GRID];
    float size_max = 0.0f;
    int ix, iy, best_x = 0, best_y = 0;
    double fraction, bound_px;
    if (validate_params(cam, why)) {
        return 1;
    }
    fraction = limits->has_limits ? limits->max_distortion_fraction : PARAMS_MAX_DISTORTION_FRACTION;
    /* math.hypot of two whole numbers <= 2^24: their squares' sum is exact, so its sqrt is the rounded hypot */
    bound_px = fraction * 0.5 * sqrt(cam->size[0] * cam->size[0] + cam->size[1] * cam->size[1]);
    grid(cam->size[0], xs);
    grid(cam->size[1], ys);
    for (iy = 0; iy < PARAMS_GRID; ++iy) {
        for (ix = 0; ix < PARAMS_GRID; ++ix) {
            float size = displacement(xs[ix] - cam->theta[1], ys[iy] - cam->theta[2], cam->theta);
            if (isnan(size)) {
                size = INFINITY;
            }
            if ((ix == 0 && iy == 0) || size > size_max) {
                size_max = size;
                best_x = ix;
                best_y = iy;
            }
        }
    }
    if (!((double)size_max <= bound_px)) {
        refuse(why, "distortion", "implausible: displacement ");
        pyformat_g(why, (double)size_max, 3u);
        pyformat_str(why, " px at pixel (");
        pyformat_f0(why, (double)xs[best_x]);
        pyformat_str(why, ", ");
        pyformat_f0(why, (double)ys[best_y]);
        pyformat_str(why, ") exceeds the bound ");
        pyformat_g(why, bound_px, 3u);
        pyformat_str(why, " px (");
        pyformat_percent0(why, fraction);
        pyformat_str(why, " of the half-diagonal)");
        return 1;
    }
    if (!limits->has_limits) {
        return 0;
    }
    if (!(fabs(cam->f_mm - limits->design_focal_length_mm) <=
          limits->focal_tolerance * limits->design_focal_length_mm)) {
        refuse(why, "focal_length_mm", "implausible: ");
        pyformat_g(why, cam->f_mm, 6u);
        pyformat_str(why, " mm is more than ");
        pyformat_percent0(why, limits->focal_tolerance);
        pyformat_str(why, " from the ");
        pyformat_str(why, limits->design_name);
        pyformat_str(why, " ");
        pyformat_g(why, limits->design_focal_length_mm, 6u);
        pyformat_str(why, " mm");
        return 1;
    }
    return limits->fixed_point ? refuse_fixed(cam, why) : 0;
}

static int validate_sigma(const float *sigma, pyformat_text_t *why)
{
    int i;
    for (i = 0; i < 10; ++i) {
        const double v = (double)sigma[i];
        if (isnan(v)) {
            continue;
        }
        if (!isfinite(v)) {
            refuse(why, SIGMA_FIELDS[i], "must be finite (or NaN/null = unknown), got ");
            pyformat_repr(why, v);
            return 1;
        }
        if (v < 0.0) {
            refuse(why, SIGMA_FIELDS[i], "a 1-sigma must be >= 0, got ");
            pyformat_repr(why, v);
            return 1;
        }
    }
    return 0;
}

int params_check_table(const uint8_t table[ST_PARAM_TABLE_BYTES], const params_limits_t *limits,
                       pyformat_text_t *why)
{
    float values[ST_PARAM_N_FIELDS];
    camera_t cam;
    int i;
    st_param_table_decode(table, values);
    for (i = 0; i < 2; ++i) { /* params_from_dict: the image size must be a whole number of pixels */
        const double n = (double)values[ST_PARAM_IMAGE_WIDTH_PX + i];
        if (!is_whole(n)) {
            refuse(why, IMAGE_FIELDS[i], "expected a whole number of pixels, got ");
            pyformat_repr(why, n);
            return 1;
        }
        cam.size[i] = n == 0.0 ? 0.0 : n; /* int(-0.0) is 0 */
    }
    cam.f_mm = (double)values[ST_PARAM_FOCAL_LENGTH_MM];
    cam.pitch_um = (double)values[ST_PARAM_PIXEL_PITCH_UM];
    cam.pp[0] = (double)values[ST_PARAM_PRINCIPAL_POINT_X_PX];
    cam.pp[1] = (double)values[ST_PARAM_PRINCIPAL_POINT_Y_PX];
    /* CameraParams.model_vector(float32): F = 1000 f / p in float64, then every slot rounded to float32 */
    cam.theta[0] = (float)(1000.0 * cam.f_mm / cam.pitch_um);
    cam.theta[1] = values[ST_PARAM_PRINCIPAL_POINT_X_PX];
    cam.theta[2] = values[ST_PARAM_PRINCIPAL_POINT_Y_PX];
    for (i = 0; i < 7; ++i) {
        cam.theta[3 + i] = values[ST_PARAM_K1 + i];
    }
    if (check_plausible(&cam, limits, why)) {
        return 1;
    }
    return validate_sigma(&values[ST_PARAM_SIGMA_OFFSET], why);
}
