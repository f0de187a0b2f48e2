/* apparent.h: the per-star apparent place, a translation of onboard/apparent.py's parts a sensor runs per star:
 * the fixed-point apparent_place_vectors_q30 (space motion, light deflection by the Sun, second-order aberration as
 * Q48 changes added to the catalogue vector, the integer normalisation, the rotation to the true equator and
 * equinox of date), bit-exact with the Python model, and the float32 relativistic aberration change (used by the
 * site's diurnal aberration).
 *
 * The per-instant quantities (the Earth's barycentric state, the GCRS -> TOD matrix) are computed once per frame
 * (onboard.apparent.fixed_instant, soft float64 on a sensor) and enter as apparent_instant_t. Formats
 * (onboard/apparent.py's table): r0 Q30, proper motion Q46 rad/yr (|pm| <= 2^-14), years Q20 (<= 2^7), parallax
 * Q48 rad (<= 2^-17), Earth position Q30 AU, deflection constant Q70, velocity beta Q44 (<= 2^-13), matrix Q30;
 * every product below 2^62 inside those ranges (no overflow, nothing saturates). */
#ifndef ONBOARD_APPARENT_H
#define ONBOARD_APPARENT_H

#include <stddef.h>
#include <stdint.h>

#include "timescale.h"

#define APPARENT_PM_FRAC_BITS 46
#define APPARENT_YEARS_FRAC_BITS 20
#define APPARENT_PARALLAX_FRAC_BITS 48
#define APPARENT_CHANGE_FRAC_BITS 48
#define APPARENT_DEFLECTION_K_FRAC_BITS 70
#define APPARENT_ABERRATION_BETA_FRAC_BITS 44
/* 1 + p.e is clamped at 2^-5 in Q30 (stars >= 14.4 deg from the Sun are exact). */
#define APPARENT_MIN_ONE_PLUS_PE_Q30 ((int64_t)1 << 25)

/* onboard.apparent.FixedInstant. */
typedef struct {
    int64_t years_q20;
    int64_t earth_bary_q30[3];
    int64_t sun_to_earth_q30[3];
    int64_t deflection_k_q70;
    int64_t beta_q44[3];
    int64_t tod_q30[3][3]; /* GCRS -> TOD */
} apparent_instant_t;

/* Catalogue vectors (Q30), proper motions (Q46 rad/yr), parallaxes (Q48 rad) -> apparent directions in TOD (Q30). */
void apparent_place_vectors_q30(const int64_t (*r0_q30)[3], const int64_t (*pm_q46)[3], const int64_t *parallax_q48,
                                size_t n, const apparent_instant_t *inst, int64_t (*out_q30)[3]);

/* Relativistic aberration change of direction p by velocity v (units of c), float32 (ERFA ab without its 1e-12
 * potential term): (w1 v - (p.v + v^2 / (1 + bm1)) p) / (1 + p.v). */
void apparent_aberration_change(const float p[3], const float velocity_c[3], float change[3]);

/* float32 ------------------------------------------------------------------------------------------------ */
/* The Earth's barycentric position [AU], barycentric velocity [AU/day] and heliocentric position [AU], GCRS axes,
 * at the TT instant: the compact model of onboard.apparent.earth_barycentric_state (Keplerian Earth-Moon
 * barycentre, circular Moon, the Sun's reflex motion due to Jupiter and Saturn; Standish's elements). */
void apparent_earth_barycentric_state(timescale_time_t t_tt, float earth_p[3], float earth_v[3], float earth_h[3]);
/* Catalogue vectors (unit, proper motion [rad/yr], parallax [mas]) at epoch_jyear -> geocentric apparent
 * directions in the true equator and equinox of date (onboard.apparent.apparent_place_vectors, geocentric). */
void apparent_place_vectors(const float (*r0)[3], const float (*pm_rad_yr)[3], const float *parallax_mas, size_t n,
                            double epoch_jyear, timescale_time_t t_tt, float (*out)[3]);

#endif
