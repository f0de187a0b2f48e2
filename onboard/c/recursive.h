/* recursive.h: the onboard recursive camera calibration from interstar angles, a translation of
 * onboard/recursive.py (float32 filter) with its fixed-point front end (onboard.fixedpoint.update).
 *
 * State: a subset of theta = (F, x0, y0, k1, k2, k3, p1, p2, s1, s2) as a scaled deviation from the nominal,
 * theta = theta_nom + s x (s the prior 1-sigma), x held as x_hi + x_lo (compensated), covariance in U-D form
 * (ud.h). Per frame: time update (burn-in forgetting, random walks), gating of the 2N - 3 independent pairs at the
 * prior with removal of misidentified stars, whitening by the Cholesky factor of the pair covariance, iterated
 * Bierman updates, post-fit editing (the frame redone once without the stars it rejects), the focal drift detector.
 * Work per frame is bounded by RECURSIVE_MAX_STARS (recursive_update_cost_flops); every buffer is in the state,
 * sized at compile time; nothing is allocated, nothing recurses.
 *
 * The Python model computes a few per-frame scalars in double (the burn-in factor, r_norm, the NIS sums, the
 * drift statistic): so does this translation, at the same places. */
#ifndef ONBOARD_RECURSIVE_H
#define ONBOARD_RECURSIVE_H

#include <stddef.h>
#include <stdint.h>

#include "camera.h"
#include "fixedpoint.h"
#include "interstar.h"
#include "ud.h"

#define RECURSIVE_N_PARAMS CAMERA_N_PARAMS
#define RECURSIVE_MAX_STATES UD_MAX_STATES
#define RECURSIVE_MAX_STARS INTERSTAR_MAX_STARS
#define RECURSIVE_MAX_PAIRS INTERSTAR_MAX_PAIRS
/* Longest focal-drift window (frames); the Python default is 200. */
#define RECURSIVE_MAX_DRIFT_WINDOW 256
/* Relative inflation of each pair's variance (onboard.recursive._R_JITTER): bounds R's condition number. */
#define RECURSIVE_R_JITTER 1e-4
/* Saved-state layout (onboard.recursive.save_state): magic "RCS1", version, 14 int64 header words. */
#define RECURSIVE_STATE_MAGIC 0x52435331
#define RECURSIVE_STATE_VERSION 1
#define RECURSIVE_STATE_HEADER_WORDS 14
/* Largest saved state in bytes: the header plus 2 * 10 + 2 K + K^2 + 2 K + 2 W + 2 float32 values. */
#define RECURSIVE_STATE_MAX_BYTES                                                                                    \
    (8 * RECURSIVE_STATE_HEADER_WORDS +                                                                              \
     4 * (2 * RECURSIVE_N_PARAMS + 4 * RECURSIVE_MAX_STATES + RECURSIVE_MAX_STATES * RECURSIVE_MAX_STATES +         \
          2 * RECURSIVE_MAX_DRIFT_WINDOW + 2))

typedef enum {
    RECURSIVE_OK = 0,
    RECURSIVE_ERR_CONFIG = 1,       /* a configuration or prior value out of range */
    RECURSIVE_ERR_NOT_POSITIVE = 2, /* the pair covariance lost positive definiteness (Cholesky failed) */
    RECURSIVE_ERR_FIXED_RANGE = 3,  /* the estimate left the fixed-point range (fixedpoint_camera) */
    RECURSIVE_ERR_STATE = 4         /* a saved state that cannot be restored */
} recursive_status_t;

/* Why a frame was not used (FrameResult.skipped); RECURSIVE_SKIP_NONE when it was. */
typedef enum {
    RECURSIVE_SKIP_NONE = 0,
    RECURSIVE_SKIP_FEW_STARS = 1,        /* "fewer than 3 identified stars" */
    RECURSIVE_SKIP_FEW_CONSISTENT = 2,   /* "fewer than 3 consistent stars" */
    RECURSIVE_SKIP_MOST_INCONSISTENT = 3 /* "most pairs inconsistent with the state" */
} recursive_skip_t;

/* onboard.recursive.RecursiveConfig (parameter units, f in mm). */
typedef struct {
    int32_t max_stars;               /* <= RECURSIVE_MAX_STARS */
    double centroid_noise_px;
    int32_t has_prior_sigma;         /* 0: the cold-start prior (recursive_default_prior_sigma) */
    double prior_sigma[RECURSIVE_N_PARAMS];
    double process_noise[RECURSIVE_N_PARAMS];
    double pair_gate_sigma;
    int32_t max_iterations;
    double iteration_tol;
    int32_t reopen_after_frames;
    int32_t burn_in_frames;
    double burn_in_power;
    int32_t drift_detect;
    int32_t drift_window_frames;     /* <= RECURSIVE_MAX_DRIFT_WINDOW */
    int32_t drift_start_frames;
    double drift_threshold;
    double drift_focal_mm_per_frame;
} recursive_config_t;

/* A camera parameter set (onboard.params.CameraParams): f in mm, distortion k1 k2 k3 p1 p2 s1 s2. */
typedef struct {
    double focal_length_mm;
    double pixel_pitch_um;
    double principal_point_px[2];
    int32_t image_size_px[2];
    double distortion[7];
} recursive_camera_t;

/* onboard.recursive.FrameResult. */
typedef struct {
    int32_t n_stars;
    int32_t n_used;
    int32_t n_rejected_stars;
    int32_t rejected_stars[RECURSIVE_MAX_STARS]; /* input rows */
    int32_t n_pairs;
    int32_t n_pairs_rejected;
    int32_t iterations;
    double nis;
    double focal_score;
    double focal_score_var;
    int32_t skipped;             /* recursive_skip_t */
    int32_t reopened;            /* the covariance was reopened to the prior */
} recursive_frame_result_t;

/* One linearisation of a frame (onboard.recursive._Linearised). */
typedef struct {
    size_t n_pairs;
    float e[RECURSIVE_MAX_PAIRS];
    float h[RECURSIVE_MAX_PAIRS * RECURSIVE_MAX_STATES];
    float r[RECURSIVE_MAX_PAIRS * RECURSIVE_MAX_PAIRS]; /* normalised by r_norm */
    double r_norm;
    int32_t pi[RECURSIVE_MAX_PAIRS];
    int32_t pj[RECURSIVE_MAX_PAIRS];
} recursive_linearised_t;

/* Per-frame scratch (not part of the saved state): the frame's selected stars and the filter's work arrays. */
typedef struct {
    int32_t n_sel;
    int32_t sel[RECURSIVE_MAX_STARS];         /* input rows of the selected stars */
    float xs[RECURSIVE_MAX_STARS];
    float ys[RECURSIVE_MAX_STARS];
    float rs[RECURSIVE_MAX_STARS][3];
    int32_t fixed;                            /* the residuals come from the fixed-point front end */
    int64_t x_q10[RECURSIVE_MAX_STARS];
    int64_t y_q10[RECURSIVE_MAX_STARS];
    int64_t r_q30[RECURSIVE_MAX_STARS][3];
    float theta_r[RECURSIVE_N_PARAMS];
    float u0[RECURSIVE_MAX_STATES * RECURSIVE_MAX_STATES];
    float d0[RECURSIVE_MAX_STATES];
    float xi[RECURSIVE_MAX_STATES];
    recursive_linearised_t lin;
    float b[RECURSIVE_MAX_STARS][3];
    float jb_theta[RECURSIVE_MAX_STARS][3][RECURSIVE_N_PARAMS];
    float jb_centroid[RECURSIVE_MAX_STARS][3][2];
    float jb[RECURSIVE_MAX_STARS * 3 * RECURSIVE_MAX_STATES];
    float r_used[RECURSIVE_MAX_PAIRS * RECURSIVE_MAX_PAIRS]; /* R of the pairs that passed the gate */
    float chol[RECURSIVE_MAX_PAIRS * RECURSIVE_MAX_PAIRS];
    float white[RECURSIVE_MAX_PAIRS * (RECURSIVE_MAX_STATES + 1)];
} recursive_work_t;

/* onboard.recursive.RecursiveState. */
typedef struct {
    recursive_camera_t nominal;
    recursive_config_t config;
    int32_t k;                                  /* estimated parameters */
    int32_t idx[RECURSIVE_MAX_STATES];          /* their model-vector slots, ascending */
    float theta_nom[RECURSIVE_N_PARAMS];
    float scale[RECURSIVE_N_PARAMS];
    float x_hi[RECURSIVE_MAX_STATES];
    float x_lo[RECURSIVE_MAX_STATES];
    float u[RECURSIVE_MAX_STATES * RECURSIVE_MAX_STATES];
    float d[RECURSIVE_MAX_STATES];
    float q[RECURSIVE_MAX_STATES];
    double q_drift;
    float d_prior[RECURSIVE_MAX_STATES];
    int64_t frames;
    int64_t updates;
    int32_t inconsistent_run;
    int32_t drift_on;
    int64_t drift_frame;
    double nis_sum;
    int64_t nis_count;
    int32_t window;
    int32_t ring_pos;
    int32_t ring_count;
    float ring_g[RECURSIVE_MAX_DRIFT_WINDOW];
    float ring_v[RECURSIVE_MAX_DRIFT_WINDOW];
    recursive_work_t work;
} recursive_state_t;

/* sizeof(recursive_state_t): for a host that allocates the state without this header (a ctypes binding). */
size_t recursive_state_size(void);
/* The defaults of onboard.recursive.RecursiveConfig. */
void recursive_default_config(recursive_config_t *config);
/* Cold-start prior 1-sigma per parameter (parameter units): 3 % of f, 5 % of the larger image side, and the
 * distortion coefficient that moves the detector corner by distortion_px. */
void recursive_default_prior_sigma(const recursive_camera_t *nominal, double distortion_px,
                                   double sigma[RECURSIVE_N_PARAMS]);
/* Worst-case floating-point operations of one update with n_stars stars and n_states estimated parameters. */
int64_t recursive_update_cost_flops(int32_t n_stars, int32_t n_states, const recursive_config_t *config);
/* A fresh estimator at the nominal with covariance = prior; estimated_mask bit i = ESTIMATE_NAMES[i]. */
recursive_status_t recursive_create(recursive_state_t *state, const recursive_camera_t *nominal,
                                    uint32_t estimated_mask, const recursive_config_t *config);

/* One frame, float32 precision: centroids [px] (float32), reference unit vectors r_ref (n x 3), identified
 * (nonzero = identified; NULL = all), n input rows. */
recursive_status_t recursive_update(recursive_state_t *state, const float *x_px, const float *y_px,
                                    const float (*r_ref)[3], const uint8_t *identified, size_t n,
                                    recursive_frame_result_t *result);
/* One frame, fixed precision (onboard.fixedpoint.update): centroids in the wire's Q10 steps, catalogue vectors in
 * Q30; stars off the detector are not taken. The interstar residuals come from the integer front end; the filter
 * runs in float32. Returns RECURSIVE_ERR_FIXED_RANGE when the estimate has left the fixed-point range. */
recursive_status_t recursive_update_fixed(recursive_state_t *state, const int64_t *x_q10, const int64_t *y_q10,
                                          const int64_t (*r_q30)[3], const uint8_t *identified, size_t n,
                                          recursive_frame_result_t *result);

/* The estimated model vector theta_nom + s (x_hi + x_lo) in double (F in px). */
void recursive_state_vector(const recursive_state_t *state, double theta[RECURSIVE_N_PARAMS]);
/* 1-sigma of each parameter in parameter units (f in mm), NaN where not estimated. */
void recursive_sigma(const recursive_state_t *state, double sigma[RECURSIVE_N_PARAMS]);
/* sum(g) / sqrt(lambda sum(var)) over the drift window; NaN until it is full or when f is not estimated. */
double recursive_drift_statistic(const recursive_state_t *state);

/* The state as onboard.recursive.save_state's bytes (float32 data); returns the length written (0: too small). */
size_t recursive_save_state(const recursive_state_t *state, uint8_t *blob, size_t capacity);
/* Rebuild a state saved by recursive_save_state (or the Python model, float32) for the same nominal. */
recursive_status_t recursive_restore_state(recursive_state_t *state, const uint8_t *blob, size_t length,
                                           const recursive_camera_t *nominal, const recursive_config_t *config);

#endif
