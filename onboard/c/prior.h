/* prior.h: the 1-sigma prior a parameter set carries and how the estimator starts from it, a translation of
 * onboard/prior.py (the numerical part: the file-field parsing stays on the host).
 *
 * A sigma is NaN or 0 ("unknown": that parameter starts from the cold-start prior) or finite > 0; negative or
 * infinite is refused. A refined sigma is inflated by PRIOR_CORRELATION_INFLATION = 2 (the set carries marginal
 * sigmas; the largest eigenvalue of a calibration's correlation matrix is bounded by 4), and the burn-in is switched
 * off when every estimated parameter has a refined prior. */
#ifndef ONBOARD_PRIOR_H
#define ONBOARD_PRIOR_H

#include <stdint.h>

#include "recursive.h"

#define PRIOR_CORRELATION_INFLATION 2.0

/* Index of the first refused sigma (negative or infinite), or -1 when all are acceptable. */
int32_t prior_validate_sigma(const double sigma[RECURSIVE_N_PARAMS]);
/* Bit i set when sigma[i] is a usable prior (finite and > 0); sigma NULL: none. */
uint32_t prior_refined_mask(const double *sigma);
/* inflation x the set's sigma where usable, else cold (NULL: recursive_default_prior_sigma of the nominal). */
void prior_sigma(const recursive_camera_t *nominal, const double *sigma, const double *cold, double inflation,
                 double out[RECURSIVE_N_PARAMS]);
/* config with the prior taken from sigma, the burn-in off when every estimated parameter (estimated_mask) has a
 * refined prior (and the drift detector allowed to start once its window is full); unchanged without sigma. */
void prior_config(const recursive_config_t *config, const recursive_camera_t *nominal, const double *sigma,
                  uint32_t estimated_mask, recursive_config_t *out);

#endif
