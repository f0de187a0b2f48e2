/* interstar.h: interstar-angle measurements in float32, a translation of onboard/interstar.py.
 *
 * e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 (seed 000 eq. 3, seed 004 eq. 1 in the difference form) over the
 * 2n - 3 independent pairs (0,1), (0,k), (1,k) of stars ordered with a well-separated base pair first. */
#ifndef ONBOARD_INTERSTAR_H
#define ONBOARD_INTERSTAR_H

#include <stddef.h>
#include <stdint.h>

/* Stars per frame the estimator takes at most (onboard.recursive.RecursiveConfig.max_stars's default): fixes
 * every per-frame buffer of the C core. */
#define INTERSTAR_MAX_STARS 32
/* Independent pairs of a frame at most: 2 N - 3. */
#define INTERSTAR_MAX_PAIRS (2 * INTERSTAR_MAX_STARS - 3)

/* The 2n - 3 pairs (0,1), then (0,k) and (1,k) for k >= 2; returns their number (0 for n < 2). */
size_t interstar_independent_pairs(size_t n_stars, int32_t *pi, int32_t *pj);

/* Permutation putting a well-separated base pair first: the star farthest from the mean, then the star farthest
 * from that one, then the others in order. */
void interstar_order_for_pairs(const float *x_px, const float *y_px, size_t n, int32_t *order);

/* Residuals e (n_pairs) of unit vectors b and reference vectors r (n x 3). */
void interstar_difference_residuals(const float (*b)[3], const float (*r)[3], const int32_t *pi, const int32_t *pj,
                                    size_t n_pairs, float *e);

/* dh/dtheta of the prediction h_ij = -|b_i - b_j|^2 / 2: h[p * k + c] = -(b_i - b_j)^T (J_i - J_j), for
 * jb = db/dtheta stored jb[(star * 3 + component) * k + column]. */
void interstar_difference_jacobian(const float (*b)[3], const float *jb, size_t k, const int32_t *pi,
                                   const int32_t *pj, size_t n_pairs, float *h);

/* Covariance r (n_pairs x n_pairs, row-major) of the pair predictions from isotropic centroid noise sigma_px, with
 * jc = db/d(x, y) (n x 3 x 2). */
void interstar_pair_covariance(const float (*b)[3], const float (*jc)[3][2], const int32_t *pi, const int32_t *pj,
                               size_t n_pairs, double sigma_px, float *r);

#endif
