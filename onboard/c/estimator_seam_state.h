/* estimator_seam_state.h: the definition of the estimator state of estimator_seam.c (the numerical core behind the
 * firmware's estimator seam), so an integrator reserves it statically, its size known at compile time:
 *
 *     #include "estimator_seam_state.h"
 *     static struct estimator_seam_state est;          (sizeof est: ESTIMATOR_SEAM_STATE_BYTES)
 *     firmware_init(&fw, &store, &est, &config, &budget);
 *
 * A build without an estimator (estimator_none.c instead of estimator_seam.c) does not include this header and
 * passes NULL. estimator_seam_state_bytes() returns the same size at run time (for a caller that cannot see this
 * header, e.g. a foreign-function binding). */
#ifndef ESTIMATOR_SEAM_STATE_H
#define ESTIMATOR_SEAM_STATE_H

#include <stdint.h>

#include "estimator_seam.h"
#include "recursive.h"

#ifdef __cplusplus
extern "C" {
#endif

struct estimator_seam_state {
    recursive_state_t rec;
    uint32_t precision;
    /* the frame in the estimator's precision (up to ESTIMATOR_SEAM_MAX_STARS input rows) */
    float x_px[ESTIMATOR_SEAM_MAX_STARS];
    float y_px[ESTIMATOR_SEAM_MAX_STARS];
    float r_ref[ESTIMATOR_SEAM_MAX_STARS][3];
    int64_t x_q10[ESTIMATOR_SEAM_MAX_STARS];
    int64_t y_q10[ESTIMATOR_SEAM_MAX_STARS];
    int64_t r_q30[ESTIMATOR_SEAM_MAX_STARS][3];
    uint8_t usable[ESTIMATOR_SEAM_MAX_STARS];
};

/* the state's size [bytes], a compile-time constant */
#define ESTIMATOR_SEAM_STATE_BYTES (sizeof(struct estimator_seam_state))

#ifdef __cplusplus
}
#endif
#endif /* ESTIMATOR_SEAM_STATE_H */
