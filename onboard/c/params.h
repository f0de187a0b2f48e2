/* params.h: the sensor-side checks of a parameter set, the C form of onboard.params (validate_params,
 * check_plausible in float32, the sensor's precision) and onboard.prior.validate_sigma, as onboard.banks.check_table
 * runs them on a staged table. The refusal text is the reference model's ParameterError text, byte for byte
 * ("field: reason", numbers formatted as Python formats them: pyformat.h).
 *
 * Float32 arithmetic in the reference's operation order (numpy evaluates left to right, one rounding per
 * operation): compile with -ffp-contract=off (no fused multiply-add). hypotf is the C library's, as numpy's. */
#ifndef PARAMS_H
#define PARAMS_H

#include <stdint.h>

#include "pyformat.h"
#include "st_param_table.h"

#ifdef __cplusplus
extern "C" {
#endif

/* onboard.params.MAX_IMAGE_SIDE_PX */
#define PARAMS_MAX_IMAGE_SIDE_PX 16777216.0
/* onboard.params.MAX_CORNER_RADIUS_PX: the farthest corner's distance from the principal point, 2^18 px (the float32
 * Jacobian column of k3, u r^6 <= r^7, finite) */
#define PARAMS_MAX_CORNER_RADIUS_PX 262144.0
/* onboard.params._MONOTONIC_GRID: points per detector side of the monotonicity and displacement grids */
#define PARAMS_GRID 17
/* onboard.params.MAX_DISTORTION_FRACTION, FOCAL_TOLERANCE */
#define PARAMS_MAX_DISTORTION_FRACTION 0.05
#define PARAMS_FOCAL_TOLERANCE 0.05

/* onboard.params.PlausibilityLimits (has_limits = 0: None, no focal-length rule) */
typedef struct {
    uint32_t has_limits;
    double design_focal_length_mm;
    double focal_tolerance;
    double max_distortion_fraction;
    const char *design_name; /* "design value" by default */
    uint32_t fixed_point;    /* the sensor runs the fixed-point front end: a set must lie in its range (fixedpoint.h) */
} params_limits_t;

/* The limits a sensor declares for its design focal length, the other fields at their defaults. */
params_limits_t params_default_limits(double design_focal_length_mm);

/* onboard.banks.check_table: 0 if the table is usable, else 1 and the refusal text in `why` (cut at
 * PYFORMAT_TEXT_MAX bytes). Rules in the reference's order: the image size a whole number
 * (params_from_dict), validate_params, the distortion bound, the focal range, on a fixed-point sensor the range of
 * its formats (check_plausible), validate_sigma. */
int params_check_table(const uint8_t table[ST_PARAM_TABLE_BYTES], const params_limits_t *limits,
                       pyformat_text_t *why);

#ifdef __cplusplus
}
#endif
#endif /* PARAMS_H */
