/* attitude.h: attitude from matched star vectors in float32, a translation of onboard/attitude.py's
 * attitude_from_vectors: the C with b = C r minimising Wahba's loss sum w_i |b_i - C r_i|^2.
 *
 * The starting solution is Markley's SVD form C = U diag(1, 1, det U det V) V^T of the attitude profile matrix
 * B = sum w b r^T (Markley 1988), here with V and the singular values from the cyclic Jacobi eigen-decomposition of
 * B^T B (a fixed number of sweeps: bounded work), u_k = B v_k / s_k for the two largest, and the third column
 * u_0 x u_1. As in the reference, ATTITUDE_REFINEMENT_STEPS Gauss-Newton steps on the same loss follow, which reach
 * the float32 floor whatever solver gave the start (the golden vectors' tolerance says so). */
#ifndef ONBOARD_ATTITUDE_H
#define ONBOARD_ATTITUDE_H

#include <stddef.h>

/* Gauss-Newton steps after the SVD (onboard.attitude._REFINEMENT_STEPS). */
#define ATTITUDE_REFINEMENT_STEPS 2
/* Second singular value of B relative to the first below which the stars are treated as collinear. */
#define ATTITUDE_COLLINEAR_RATIO 1e-6f
/* Jacobi sweeps over the 3 x 3 B^T B (quadratic convergence: 6 sweeps are far below float32's resolution). */
#define ATTITUDE_JACOBI_SWEEPS 8

typedef enum {
    ATTITUDE_OK = 0,
    ATTITUDE_ERR_DEGENERATE = 1 /* fewer than two non-parallel stars */
} attitude_status_t;

/* Attitude c (3 x 3, row-major: b = C r) from n matched unit vectors b, r and weights w (NULL: equal). */
attitude_status_t attitude_from_vectors(const float (*b)[3], const float (*r)[3], const float *weights, size_t n,
                                        float c[3][3]);

/* Rotation matrix R with R p = p + phi x p + ... for a small rotation vector phi (Rodrigues, series to phi^4). */
void attitude_small_rotation(const float phi[3], float out[3][3]);

#endif
