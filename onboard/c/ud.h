/* ud.h: U-D factorised covariance P = U diag(d) U^T, a translation of onboard/ud.py (Bierman 1977 ch. V; Agee and
 * Turner 1972). In place on caller-owned arrays; U is k x k row-major (u[i * k + j]), unit upper triangular, with
 * k <= UD_MAX_STATES. No allocation: the scratch lives on the stack, sized by UD_MAX_STATES. */
#ifndef ONBOARD_UD_H
#define ONBOARD_UD_H

#include <stddef.h>

/* The estimator's states at most: the 10 camera parameters (onboard.params.N_PARAMS). */
#define UD_MAX_STATES 10

/* Bierman's scalar measurement update for y = h . x + noise of unit variance (the caller whitens), in place on
 * (u, d, xi). Returns the innovation y - h . xi and writes its variance h P h + 1 (both before the update) to *s.
 * The column recursion written as the Python's cumulative sums (the same additions in the same order). */
float ud_bierman_update(float *u, float *d, float *xi, const float *h, float y, size_t k, float *s);

/* U D U^T <- U D U^T + c a a^T for c >= 0 (Agee-Turner rank-one update); a (k values) is overwritten. */
void ud_agee_turner_update(float *u, float *d, float *a, float c, size_t k);

/* P = U diag(d) U^T (k x k, row-major), in double (reporting only). */
void ud_covariance(const float *u, const float *d, size_t k, double *p);

#endif
