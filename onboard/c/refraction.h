/* refraction.h: refraction by addition for ground and ship-borne sensors (seed 001 sec. 4), a translation of
 * onboard/refraction.py's per-star part: float32 (zenith geometry, the refraction from the true zenith distance by
 * Newton's method, the rotation in the vertical) and the fixed-point twin (topocentric_observed_q30: first-order
 * diurnal aberration, then the refraction in integers), bit-exact with the Python model.
 *
 * R = A tan z_a + B tan^3 z_a (A, B configuration values, onboard.refraction.refraction_coefficients); solved for
 * the true zenith distance z_t = z_a + R(z_a) by REFRACTION_TRUE_ZENITH_NEWTON_STEPS Newton steps from z_a = z_t.
 * Fixed formats (onboard/refraction.py's table): r, zenith, result Q30; beta = v / c Q48 (|beta| <= 2^-18); A, B Q56
 * (|A| <= 2^-10, |B| <= 2^-19); tan z Q24; tan^2 z Q16; R Q36; every product below 2^62.2 inside those ranges, so
 * no int64 overflow (nothing saturates; the ranges are the caller's contract, as in the Python model). */
#ifndef ONBOARD_REFRACTION_H
#define ONBOARD_REFRACTION_H

#include <stddef.h>
#include <stdint.h>

#define REFRACTION_TRUE_ZENITH_NEWTON_STEPS 2
/* Below this cosine of zenith distance (about 87 deg) refraction is frozen at its value there. */
#define REFRACTION_MIN_COS_ZENITH 0.05
#define REFRACTION_BETA_FRAC_BITS 48
#define REFRACTION_COEF_FRAC_BITS 56
#define REFRACTION_R_FRAC_BITS 36
#define REFRACTION_TAN_FRAC_BITS 24
#define REFRACTION_TAN2_FRAC_BITS 16

/* float32 ------------------------------------------------------------------------------------------------- */
/* (cos z, sin z, tangential = U - (r.U) r) of n unit directions about the zenith U. */
void refraction_zenith_geometry(const float (*r)[3], size_t n, const float zenith[3], float *cos_z, float *sin_z,
                                float (*tangential)[3]);
/* R [rad] with z_t = z_a + R(z_a), from cos and sin of the true zenith distance (Newton, REFRACTION_TRUE_ZENITH_...
 * steps, the first ERFA atioq's formula). a_rad, b_rad are rounded to float32 as the Python code casts them. */
float refraction_from_true_zenith(float cos_zt, float sin_zt, double a_rad, double b_rad);
/* r rotated by angle toward the zenith, keeping the azimuth: r cos(angle) + t sin(angle) / sin z (at the zenith the
 * ratio is angle_over_sin_z_at_zenith). */
void refraction_rotate_in_vertical(const float r[3], float sin_z, const float tangential[3], float angle_rad,
                                   float angle_over_sin_z_at_zenith, float out[3]);
/* True directions lifted toward the zenith by the refraction (A, B): onboard.refraction.refract_toward_zenith with
 * the model's coefficients given. */
void refraction_refract_toward_zenith(const float (*r)[3], size_t n, const float zenith[3], double a_rad,
                                      double b_rad, float (*out)[3]);

/* fixed point --------------------------------------------------------------------------------------------- */
/* cos R and sin R in Q30 from R in Q36 (|R| < 2^-3.9): cos = 1 - R^2/2 + R^4/24, sin = R - R^3/6. */
void refraction_cos_sin_q30(int64_t r_q36, int64_t *cos_q30, int64_t *sin_q30);
/* R [rad] in Q36 from cos and sin of the true zenith distance (Q30), A and B in Q56. */
int64_t refraction_from_true_zenith_q36(int64_t cos_q30, int64_t sin_q30, int64_t a_q56, int64_t b_q56);
/* Geocentric apparent unit vectors (Q30) -> as observed at the site (Q30): diurnal aberration by beta (Q48) to
 * first order, then (with_refraction) the refraction by addition toward the zenith (Q30) with A, B (Q56). */
void refraction_topocentric_observed_q30(const int64_t (*r_q30)[3], size_t n, const int64_t zenith_q30[3],
                                         const int64_t beta_q48[3], int with_refraction, int64_t a_q56,
                                         int64_t b_q56, int64_t (*out_q30)[3]);

#endif
