/* prior.c: onboard/prior.py's numerical part (see prior.h). */
#include "prior.h"

#include <math.h>

int32_t prior_validate_sigma(const double sigma[RECURSIVE_N_PARAMS])
{
    int32_t i;
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        if (isnan(sigma[i])) {
            continue;
        }
        if (!isfinite(sigma[i]) || sigma[i] < 0.0) {
            return i;
        }
    }
    return -1;
}

uint32_t prior_refined_mask(const double *sigma)
{
    uint32_t mask = 0u;
    int i;
    if (sigma == NULL) {
        return 0u;
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        if (isfinite(sigma[i]) && sigma[i] > 0.0) {
            mask |= 1u << i;
        }
    }
    return mask;
}

void prior_sigma(const recursive_camera_t *nominal, const double *sigma, const double *cold, double inflation,
                 double out[RECURSIVE_N_PARAMS])
{
    double base[RECURSIVE_N_PARAMS];
    const uint32_t mask = prior_refined_mask(sigma);
    int i;
    if (cold != NULL) {
        for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
            base[i] = cold[i];
        }
    } else {
        recursive_default_prior_sigma(nominal, 5.0, base);
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        out[i] = (mask >> i) & 1u ? inflation * sigma[i] : base[i];
    }
}

void prior_config(const recursive_config_t *config, const recursive_camera_t *nominal, const double *sigma,
                  uint32_t estimated_mask, recursive_config_t *out)
{
    const uint32_t mask = prior_refined_mask(sigma);
    *out = *config;
    if (mask == 0u) {
        return;
    }
    prior_sigma(nominal, sigma, config->has_prior_sigma ? config->prior_sigma : NULL, PRIOR_CORRELATION_INFLATION,
                out->prior_sigma);
    out->has_prior_sigma = 1;
    if ((mask & estimated_mask) != estimated_mask) {
        return;
    }
    out->burn_in_frames = 0;
    if (config->drift_window_frames < out->drift_start_frames) {
        out->drift_start_frames = config->drift_window_frames;
    }
}
