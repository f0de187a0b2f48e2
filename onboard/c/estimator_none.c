/* estimator_none.c: the estimator seam of a build without an onboard estimator (estimator_seam.h). The firmware
 * never starts or updates it (estimator_seam_available() == 0); the functions exist so the core links. */
#include "estimator_seam.h"

struct estimator_seam_state {
    uint32_t unused;
};

int estimator_seam_available(void) { return 0; }

size_t estimator_seam_state_bytes(void) { return sizeof(struct estimator_seam_state); }

int estimator_seam_start(estimator_seam_state_t *state, const estimator_seam_config_t *config,
                         const float table[ST_PARAM_N_FIELDS])
{
    (void)state;
    (void)config;
    (void)table;
    return 1;
}

int estimator_seam_update(estimator_seam_state_t *state, uint32_t n, const double *x_px, const double *y_px,
                          const double *r_ref, const uint8_t *identified)
{
    (void)state;
    (void)n;
    (void)x_px;
    (void)y_px;
    (void)r_ref;
    (void)identified;
    return 1;
}

void estimator_seam_estimate(const estimator_seam_state_t *state, float values[ESTIMATOR_SEAM_N_PARAMS],
                             float sigma[ESTIMATOR_SEAM_N_PARAMS], uint32_t *estimated_mask, uint32_t *n_updates)
{
    uint32_t i;
    (void)state;
    for (i = 0u; i < ESTIMATOR_SEAM_N_PARAMS; ++i) {
        values[i] = 0.0f;
        sigma[i] = 0.0f;
    }
    *estimated_mask = 0u;
    *n_updates = 0u;
}

uint64_t estimator_seam_cost_flops(const estimator_seam_config_t *config, uint32_t n_stars)
{
    (void)config;
    (void)n_stars;
    return 0u;
}
