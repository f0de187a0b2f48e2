/* estimator_seam.c: the estimator seam of the C firmware core (estimator_seam.h) implemented with the numerical core:
 * onboard.firmware.RecursiveEstimator translated. start builds the prior as RecursiveEstimator.start does
 * (prior_config from the active set's sigma, then recursive_create); update converts the frame to the sensor's
 * precision exactly as onboard.firmware.estimator_update does (float32: each value rounded to float32; fixed:
 * onboard.fixedpoint.frame_front_end's Q10 centroids and Q30 references) and runs recursive_update(_fixed);
 * estimate and cost_flops are RecursiveEstimator.estimate and cost_flops. */
#include "estimator_seam.h"
#include "estimator_seam_state.h"

#include <float.h>
#include <math.h>

#include "fixedpoint.h"
#include "params.h"
#include "prior.h"
#include "recursive.h"

int estimator_seam_available(void)
{
    return 1;
}

size_t estimator_seam_state_bytes(void)
{
    return sizeof(struct estimator_seam_state);
}

/* RecursiveEstimator's configuration: RecursiveConfig(centroid_noise_px=..., drift_focal_mm_per_frame=...), every
 * other field its default (a drift walk of 0 keeps the default too). */
static void seam_config(const estimator_seam_config_t *config, recursive_config_t *out)
{
    recursive_default_config(out);
    out->centroid_noise_px = config->centroid_noise_px;
    if (config->drift_focal_mm_per_frame > 0.0) {
        out->drift_focal_mm_per_frame = config->drift_focal_mm_per_frame;
    }
}

int estimator_seam_start(estimator_seam_state_t *state, const estimator_seam_config_t *config,
                         const float table[ST_PARAM_N_FIELDS])
{
    recursive_camera_t nominal;
    recursive_config_t base, cfg;
    double sigma[RECURSIVE_N_PARAMS];
    const double width = (double)table[ST_PARAM_IMAGE_WIDTH_PX], height = (double)table[ST_PARAM_IMAGE_HEIGHT_PX];
    int i;
    /* banks.table_to_params: an image size that is not a whole number cannot start an estimator; any size the checks
     * accept (1..2^24 px a side, params.h) does, as the reference model's (a 65535 px bound here once left a wider
     * detector without an estimate in C while the Python model ran one) */
    if (config->precision > ESTIMATOR_SEAM_FIXED || !(width >= 1.0 && width <= PARAMS_MAX_IMAGE_SIDE_PX) ||
        !(height >= 1.0 && height <= PARAMS_MAX_IMAGE_SIDE_PX) || width != floor(width) || height != floor(height)) {
        return 1;
    }
    nominal.focal_length_mm = (double)table[ST_PARAM_FOCAL_LENGTH_MM];
    nominal.pixel_pitch_um = (double)table[ST_PARAM_PIXEL_PITCH_UM];
    nominal.principal_point_px[0] = (double)table[ST_PARAM_PRINCIPAL_POINT_X_PX];
    nominal.principal_point_px[1] = (double)table[ST_PARAM_PRINCIPAL_POINT_Y_PX];
    nominal.image_size_px[0] = (int32_t)width;
    nominal.image_size_px[1] = (int32_t)height;
    for (i = 0; i < 7; ++i) {
        nominal.distortion[i] = (double)table[ST_PARAM_K1 + i];
    }
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        sigma[i] = (double)table[ST_PARAM_SIGMA_OFFSET + (unsigned)i];
    }
    seam_config(config, &base);
    prior_config(&base, &nominal, sigma, config->estimate_mask, &cfg);
    state->precision = config->precision;
    return recursive_create(&state->rec, &nominal, config->estimate_mask, &cfg) == RECURSIVE_OK ? 0 : 1;
}

/* double -> float32, NaN for a value outside float32's range (a defined conversion in every case). */
static float to_float(double v)
{
    return fabs(v) <= (double)FLT_MAX ? (float)v : (float)NAN;
}

int estimator_seam_update(estimator_seam_state_t *state, uint32_t n, const double *x_px, const double *y_px,
                          const double *r_ref, const uint8_t *identified)
{
    recursive_frame_result_t result;
    recursive_status_t status;
    uint32_t i;
    int c;
    if (n > ESTIMATOR_SEAM_MAX_STARS) {
        return 1;
    }
    if (state->precision == ESTIMATOR_SEAM_FIXED) {
        /* onboard.fixedpoint.frame_front_end: usable = identified and finite; Q10 centroids, Q30 references */
        for (i = 0u; i < n; ++i) {
            int usable = identified[i] != 0u && isfinite(x_px[i]) && isfinite(y_px[i]);
            for (c = 0; c < 3; ++c) {
                usable = usable && isfinite(r_ref[3u * i + (unsigned)c]);
            }
            state->usable[i] = (uint8_t)usable;
            state->x_q10[i] = usable ? fixedpoint_quantise_px(x_px[i]) : 0;
            state->y_q10[i] = usable ? fixedpoint_quantise_px(y_px[i]) : 0;
            for (c = 0; c < 3; ++c) {
                state->r_q30[i][c] = usable ? fixedpoint_quantise_unit_q30(r_ref[3u * i + (unsigned)c]) : 0;
            }
        }
        status = recursive_update_fixed(&state->rec, state->x_q10, state->y_q10, (const int64_t (*)[3])state->r_q30,
                                        state->usable, n, &result);
    } else {
        /* each value rounded to float32 (numpy's astype); a value beyond float32's range (no centroid the wire can
         * carry, no unit-vector component) would make the conversion undefined in C: it becomes NaN, so the row is
         * not used (numpy would give an infinity that poisons the frame) */
        for (i = 0u; i < n; ++i) {
            state->x_px[i] = to_float(x_px[i]);
            state->y_px[i] = to_float(y_px[i]);
            for (c = 0; c < 3; ++c) {
                state->r_ref[i][c] = to_float(r_ref[3u * i + (unsigned)c]);
            }
        }
        status = recursive_update(&state->rec, state->x_px, state->y_px, (const float (*)[3])state->r_ref,
                                  identified, n, &result);
    }
    return status == RECURSIVE_OK ? 0 : 1;
}

void estimator_seam_estimate(const estimator_seam_state_t *state, float values[ESTIMATOR_SEAM_N_PARAMS],
                             float sigma[ESTIMATOR_SEAM_N_PARAMS], uint32_t *estimated_mask, uint32_t *n_updates)
{
    double theta[RECURSIVE_N_PARAMS], sd[RECURSIVE_N_PARAMS];
    uint32_t mask = 0u;
    int i;
    recursive_state_vector(&state->rec, theta);
    recursive_sigma(&state->rec, sd);
    theta[0] = theta[0] * state->rec.nominal.pixel_pitch_um / 1000.0; /* f = F p / 1000 */
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        values[i] = (float)theta[i];
        sigma[i] = (float)sd[i];
    }
    for (i = 0; i < state->rec.k; ++i) {
        mask |= 1u << state->rec.idx[i];
    }
    *estimated_mask = mask;
    *n_updates = (uint32_t)state->rec.updates;
}

uint64_t estimator_seam_cost_flops(const estimator_seam_config_t *config, uint32_t n_stars)
{
    recursive_config_t cfg;
    int32_t k = 0;
    int i;
    seam_config(config, &cfg);
    for (i = 0; i < RECURSIVE_N_PARAMS; ++i) {
        k += (int32_t)((config->estimate_mask >> i) & 1u);
    }
    return (uint64_t)recursive_update_cost_flops(n_stars > 1000u ? 1000 : (int32_t)n_stars, k, &cfg);
}
