/* fixedpoint.h: the fixed-point front end of the onboard estimator, a translation of onboard/fixedpoint.py, for a
 * sensor without an FPU: Q10 centroids -> Q30 ideal offsets -> Q30 unit vectors -> Q61 interstar residuals, in
 * integers, bit-exact with the Python model (the golden vectors and whole replayed sessions prove it).
 *
 * Formats (Qn = integer times 2^-n; S = 2^s px the smallest power of two >= the longer detector side; the table of
 * onboard/fixedpoint.py's docstring gives every range): centroids Q10 px; u, v, u', v' Q30 normalised (px / S);
 * coefficients in block floating point m 2^-e with 2^27 <= |m| <= 2^28; w = (u', v', F) Q(qw); unit vectors Q30;
 * residuals Q61. Rounding: every right shift rounds to nearest, ties toward +infinity (fixedpoint_rshift_round).
 *
 * Overflow: none can occur inside the range the Python model proves (every operand below 2^34, every product below
 * 2^62.2 < 2^63), and fixedpoint_camera refuses a parameter set outside it, fixedpoint_ideal_offsets_q30 a centroid
 * off the detector; nothing saturates because nothing can reach the int64 limits. Negative numbers are never
 * shifted left (multiplied by a power of two instead) and right shifts are written as floor divisions that do not
 * depend on the compiler's implementation-defined >> of a negative value.
 *
 * fixedpoint_camera converts the float32 model vector with exact double operations (frexp, ldexp, rounding to the
 * nearest integer): once per linearisation, 10 values (a few soft-float calls on the sensor), never per star. */
#ifndef ONBOARD_FIXEDPOINT_H
#define ONBOARD_FIXEDPOINT_H

#include <stddef.h>
#include <stdint.h>

#include "camera.h"

/* Fractional bits of normalised lengths, unit vectors and the radial factor. */
#define FIXEDPOINT_Q 30
/* Bits of the centroid's fractional part on the wire (2^-10 px). */
#define FIXEDPOINT_CENTROID_FRAC_BITS 10
/* Fractional bits of the interstar residual (exact from Q30 vectors). */
#define FIXEDPOINT_E_FRAC_BITS (2 * FIXEDPOINT_Q + 1)
/* Largest detector shift s (S = 2^s px): the Q10 centroid must fit the Q(30 - s) grid. */
#define FIXEDPOINT_MAX_DETECTOR_SHIFT (FIXEDPOINT_Q - FIXEDPOINT_CENTROID_FRAC_BITS)
/* Longest focal length [px], 2^20: a Q30 unit vector's grid (F 2^-30 px on the detector) no coarser than the Q10
 * centroid's; it also keeps F / S <= 2^19, so every shift of w stays below 64 bits
 * (onboard.fixedpoint.MAX_FOCAL_PX). */
#define FIXEDPOINT_MAX_FOCAL_PX 1048576.0
/* Mantissa bits of a block-floating-point coefficient (float32's 24 bits fit exactly). */
#define FIXEDPOINT_COEF_BITS 28
/* Largest coefficient exponent (a right shift of an int64). */
#define FIXEDPOINT_COEF_MAX_EXP 62
/* Newton iterations of the reciprocal square root from the table (relative error 3.1e-2 -> 1.5e-11). */
#define FIXEDPOINT_RSQRT_ITERATIONS 3
/* Entries of the reciprocal-square-root table and the bin a >> 26 of its first entry. */
#define FIXEDPOINT_RSQRT_TABLE_SIZE 25
#define FIXEDPOINT_RSQRT_TABLE_FIRST 8
/* Newton iterations of fixedpoint_isqrt (onboard/fixedpoint.py ISQRT_ITERATIONS). */
#define FIXEDPOINT_ISQRT_ITERATIONS 8

/* 1 / sqrt(alpha) in Q30 at the centre of each bin: isqrt(2^66 / (2 i + 1)), i = 8..32. */
extern const int64_t fixedpoint_rsqrt_table_q30[FIXEDPOINT_RSQRT_TABLE_SIZE];

typedef enum {
    FIXEDPOINT_OK = 0,
    FIXEDPOINT_ERR_DETECTOR_SIZE = 1, /* detector side beyond 2^20 px */
    FIXEDPOINT_ERR_NOT_FINITE = 2,    /* a parameter is not finite */
    FIXEDPOINT_ERR_PRINCIPAL_POINT = 3, /* principal point off the detector */
    FIXEDPOINT_ERR_FOCAL = 4,         /* focal length below S / 8 */
    FIXEDPOINT_ERR_DISTORTION = 5,    /* distortion correction beyond 100 % of the radius */
    FIXEDPOINT_ERR_CENTROID = 6,      /* a centroid off the detector */
    FIXEDPOINT_ERR_FOCAL_LONG = 7     /* focal length above FIXEDPOINT_MAX_FOCAL_PX */
} fixedpoint_status_t;

/* A camera model vector in the front end's formats (onboard.fixedpoint.FixedCamera). */
typedef struct {
    int32_t s;           /* detector shift, S = 2^s px */
    int64_t x0_q;        /* Q30 normalised */
    int64_t y0_q;
    int64_t coef_m[7];   /* K1 K2 K3 P1 P2 S1 S2 normalised, m 2^-e */
    int32_t coef_e[7];
    int32_t qw;          /* fractional bits of w */
    int64_t f_w;         /* F in Q(qw) normalised */
    int32_t width_px;
    int32_t height_px;
    double theta_q[CAMERA_N_PARAMS]; /* the model vector these integers represent (exact) */
} fixedpoint_camera_t;

/* a 2^-n rounded to nearest, ties toward +infinity: floor((a + 2^(n-1)) / 2^n), 1 <= n <= 62. */
int64_t fixedpoint_rshift_round(int64_t a, int n);
/* num / den rounded to nearest, ties toward +infinity, den > 0: floor((num + floor(den / 2)) / den). */
int64_t fixedpoint_div_round(int64_t num, int64_t den);
/* Bit length of 0 <= x < 2^63 (a CLZ instruction on a sensor). */
int32_t fixedpoint_bit_length(int64_t x);
/* floor(sqrt(n)) for 0 <= n < 2^62 (Newton's method in integers). */
int64_t fixedpoint_isqrt(int64_t n);
/* 1 / sqrt(n2) for 2^50 <= n2 < 2^62 as Y 2^-30 2^-k (Y in Q30 in [2^30, 2^31]); returns Y, writes k. */
int64_t fixedpoint_rsqrt_q30(int64_t n2, int32_t *k);

/* s with S = 2^s the smallest power of two >= the longer detector side (s >= 1). */
int32_t fixedpoint_detector_shift(int32_t width_px, int32_t height_px);
/* Model vector (float32) -> the front end's formats; refuses a set outside the proved range. */
fixedpoint_status_t fixedpoint_camera(const float theta[CAMERA_N_PARAMS], int32_t width_px, int32_t height_px,
                                      fixedpoint_camera_t *cam);
/* The range condition's sum at the farthest corner (onboard.fixedpoint.distortion_share): the distortion correction
 * as a fraction of the radius, from a camera whose s, x0_q, y0_q, size and coefficients are set; <= 1 in range. */
double fixedpoint_distortion_share(const fixedpoint_camera_t *cam);
/* Whether a centroid (Q10 px) lies on the detector [-0.5, W - 0.5] x [-0.5, H - 0.5]. */
int fixedpoint_on_detector(int64_t x_q10, int64_t y_q10, int32_t width_px, int32_t height_px);
/* Measured centroid (Q10 px) -> ideal offsets (u', v'), Q30 normalised (the Weng correction, seed 000 eq. 7). */
fixedpoint_status_t fixedpoint_ideal_offsets_q30(int64_t x_q10, int64_t y_q10, const fixedpoint_camera_t *cam,
                                                 int64_t *u_ideal_q30, int64_t *v_ideal_q30);
/* Ideal offsets (Q30 normalised) -> sensor-frame unit vector in Q30. */
void fixedpoint_offsets_to_unit_q30(int64_t u_ideal_q30, int64_t v_ideal_q30, const fixedpoint_camera_t *cam,
                                    int64_t b_q30[3]);
/* Integer vector with |w_c| <= 2^30 and 2^50 <= |w|^2 < 2^62 -> w / |w| in Q30. */
void fixedpoint_normalise_q30(const int64_t w[3], int64_t out_q30[3]);
/* Measured centroid (Q10 px) -> sensor-frame unit vector (Q30): the twin of camera_pixels_to_unit. */
fixedpoint_status_t fixedpoint_pixels_to_unit_q30(int64_t x_q10, int64_t y_q10, const fixedpoint_camera_t *cam,
                                                  int64_t b_q30[3]);
/* e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 in Q61, exact, for n_pairs pairs (pi[p], pj[p]). */
void fixedpoint_difference_residuals_q61(const int64_t (*b_q30)[3], const int64_t (*r_q30)[3], const int32_t *pi,
                                         const int32_t *pj, size_t n_pairs, int64_t *e_q61);
/* Q61 residuals -> float32 (one rounding int64 -> float, then an exact power-of-two scaling). */
void fixedpoint_residuals_to_float(const int64_t *e_q61, size_t n, float *e);

/* Ground-side conversions (the centroider's output and the catalogue build; double by nature): a centroid [px] to
 * its Q10 steps (round half even, clipped to +-2^40 px first; NaN -> 0), a unit-vector component to Q30 (round half
 * even; clamped to +-2 first, NaN -> 0: only a value that is no unit-vector component is changed). */
int64_t fixedpoint_quantise_px(double value_px);
int64_t fixedpoint_quantise_unit_q30(double component);

#endif
