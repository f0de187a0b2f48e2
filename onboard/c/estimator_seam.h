/* estimator_seam.h: the C firmware core's estimator seam, the C form of onboard.firmware.EstimatorSeam.
 *
 * Owned by the firmware core (firmware.c calls it). Implemented by the numerical core in estimator_seam.c (calling
 * recursive.c, ud.c, camera.c, prior.c, fixedpoint.c ...), or by estimator_none.c in a build without an estimator
 * (hostlink/portkit/firmware_c.py compiles estimator_seam.c when it exists, else estimator_none.c). Python -> C:
 *
 *   EstimatorSeam.start(nominal, sigma)          estimator_seam_start(state, config, table)
 *       table: the active set's ST_PARAM_N_FIELDS decoded float32 fields (st_param_table_decode): the camera fields
 *       (banks.table_to_params) followed by the 1-sigma prior (banks.table_to_sigma, NaN or 0 = unknown). The
 *       implementation builds its prior as RecursiveEstimator.start does (onboard.prior.prior_config).
 *   EstimatorSeam.update(state, x, y, r, ident)  estimator_seam_update(state, n, x_px, y_px, r_ref, identified)
 *       n <= ESTIMATOR_SEAM_MAX_STARS stars: centroids [px] and reference unit vectors (row-major n x 3) as the frame
 *       and the catalogue hold them (double, as the Python firmware passes float64; the implementation converts to
 *       its precision exactly as onboard.firmware.estimator_update does), identified[i] 0/1 (rows not identified
 *       hold 0.0). Returns 0, or nonzero where the Python update raises ArithmeticError, ValueError (e.g.
 *       FixedRangeError) or LinAlgError: the firmware then counts an estimator fault and restarts from the active set.
 *   EstimatorSeam.estimate(state)                estimator_seam_estimate(state, values, sigma, &mask, &n_updates)
 *       values and 1-sigma in ESTIMATE_NAMES order (f in mm; sigma NaN where not estimated), bit i of mask =
 *       ESTIMATE_NAMES[i] estimated, n_updates = state.updates.
 *   EstimatorSeam.cost_flops(n_stars)            estimator_seam_cost_flops(config, n_stars)
 *       onboard.recursive.update_cost_flops(n_stars, number of estimated parameters, config).
 *
 * Memory: no allocation. The state is an incomplete type here; estimator_seam.c's is defined in
 * estimator_seam_state.h, so an integrator reserves it statically (flight code: `static struct estimator_seam_state
 * est;` after #include "estimator_seam_state.h", ESTIMATOR_SEAM_STATE_BYTES its size at compile time) or, from
 * Python, as a buffer of estimator_seam_state_bytes() bytes (aligned to 16 bytes). The firmware holds a pointer to
 * it; NULL = a sensor without estimator.
 * C99, no I/O, no recursion; every function does bounded work for n <= ESTIMATOR_SEAM_MAX_STARS.
 */
#ifndef ESTIMATOR_SEAM_H
#define ESTIMATOR_SEAM_H

#include <stddef.h>
#include <stdint.h>

#include "st_param_table.h"

#ifdef __cplusplus
extern "C" {
#endif

/* ESTIMATE_NAMES: f x0 y0 k1 k2 k3 p1 p2 s1 s2 */
#define ESTIMATOR_SEAM_N_PARAMS 10u
/* protocol.messages.MAX_STARS: stars in one frame */
#define ESTIMATOR_SEAM_MAX_STARS 255u

/* onboard.firmware.PRECISIONS */
enum estimator_seam_precision {
    ESTIMATOR_SEAM_FLOAT32 = 0, /* a single-precision FPU */
    ESTIMATOR_SEAM_FIXED = 1    /* no FPU: onboard.fixedpoint's integer front end, the filter in soft float32 */
};

/* The RecursiveEstimator's settings the emulator passes (hostlink/emulator/setup.py); every other
 * onboard.recursive.RecursiveConfig field keeps its default. */
typedef struct {
    uint32_t estimate_mask;  /* bit i: ESTIMATE_NAMES[i] is estimated (RecursiveEstimator.estimate_names) */
    uint32_t precision;      /* enum estimator_seam_precision */
    double centroid_noise_px; /* RecursiveConfig.centroid_noise_px (double, as the Python model keeps it) */
    /* RecursiveConfig.drift_focal_mm_per_frame: the focal random walk the drift detector switches on, 1-sigma per
     * frame [mm]; 0 (as a shorter initialiser leaves it): the default 7e-5 mm, the built-in 70 mm lens's. For another
     * lens 1e-6 x its focal length (onboard.recursive.drift_focal_mm_per_frame_for; see onboard/c/README.md). */
    double drift_focal_mm_per_frame;
} estimator_seam_config_t;

typedef struct estimator_seam_state estimator_seam_state_t;

/* 1 when this build has an estimator, 0 (estimator_none.c): the firmware then answers READ_ESTIMATE with
 * NO_ESTIMATE "this sensor has no onboard estimator", as onboard.firmware.Firmware(estimator=None) does. */
int estimator_seam_available(void);
/* sizeof(struct estimator_seam_state) */
size_t estimator_seam_state_bytes(void);
/* A fresh state from the active set (0 = started; nonzero = the set cannot start an estimator: no estimate). */
int estimator_seam_start(estimator_seam_state_t *state, const estimator_seam_config_t *config,
                         const float table[ST_PARAM_N_FIELDS]);
/* One frame (0 = done; nonzero = a numerically failed update, the state is then restarted by the caller). */
int estimator_seam_update(estimator_seam_state_t *state, uint32_t n, const double *x_px, const double *y_px,
                          const double *r_ref, const uint8_t *identified);
void estimator_seam_estimate(const estimator_seam_state_t *state, float values[ESTIMATOR_SEAM_N_PARAMS],
                             float sigma[ESTIMATOR_SEAM_N_PARAMS], uint32_t *estimated_mask, uint32_t *n_updates);
/* Declared worst-case floating-point operations of one update with n_stars identified stars. */
uint64_t estimator_seam_cost_flops(const estimator_seam_config_t *config, uint32_t n_stars);

#ifdef __cplusplus
}
#endif
#endif /* ESTIMATOR_SEAM_H */
