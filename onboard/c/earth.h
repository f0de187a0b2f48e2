/* earth.h: the GCRS -> true-of-date rotation in float32, a translation of onboard/earth.py's true_of_date_matrix
 * (IAU 2006 Fukushima-Williams precession with frame bias, IERS 2010 eq. 5.39-5.41; the 30 largest terms of the
 * IAU 2000B nutation, McCarthy & Luzum 2003) with its helpers. Matrices are row-major 3 x 3. */
#ifndef ONBOARD_EARTH_H
#define ONBOARD_EARTH_H

#include "timescale.h"

/* Terms of the truncated IAU 2000B luni-solar nutation series. */
#define EARTH_NUTATION_TERMS 30

/* Frame rotations about x, y, z by angle (ERFA's Rx, Ry, Rz conventions). */
void earth_rot_x(float angle_rad, float m[3][3]);
void earth_rot_y(float angle_rad, float m[3][3]);
void earth_rot_z(float angle_rad, float m[3][3]);
/* (gamma_bar, phi_bar - eps_0, psi_bar, eps_A - eps_0) [rad] at t_c Julian centuries TT since J2000. */
void earth_precession_offsets(float t_c, float out[4]);
/* Delaunay arguments l, l', F, D, Omega [rad] reduced to [0, 2 pi). */
void earth_delaunay_arguments(float t_c, float args[5]);
/* Nutation in longitude and obliquity (dpsi, deps) [rad], truncated IAU 2000B. */
void earth_nutation(float t_c, float *dpsi, float *deps);
/* NPB: GCRS -> true equator and equinox of date, r_tod = NPB r_gcrs, at the TT instant t_tt. */
void earth_true_of_date_matrix(timescale_time_t t_tt, float npb[3][3]);

#endif
