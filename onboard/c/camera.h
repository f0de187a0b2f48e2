/* camera.h: the camera model of docs/camera-model.md in float32, a translation of onboard/camera.py (the sensor's
 * per-frame direction and the Jacobians the recursive estimator linearises with).
 *
 * theta = (F_px, x0_px, y0_px, k1, k2, k3, p1, p2, s1, s2), the model vector (CameraParams.model_vector).
 * Source: Weng, Cohen, Herniou (1992) as seed 000 eq. 7; pinhole direction as seed 004 eq. 2. Every function
 * evaluates the Python expressions term by term in the same order (built with -ffp-contract=off: no fused
 * multiply-add), so results differ from numpy's float32 only where numpy sums in another order. */
#ifndef ONBOARD_CAMERA_H
#define ONBOARD_CAMERA_H

#include <stddef.h>
#include <stdint.h>

/* Slots of the model vector (onboard.params.ESTIMATE_NAMES order, F in px). */
#define CAMERA_N_PARAMS 10

/* Weng distortion (dx, dy) [px] at measured offsets (u, v) from the principal point (seed 000 eq. 7). */
void camera_distortion_px(float u, float v, const float theta[CAMERA_N_PARAMS], float *dx, float *dy);

/* Partial derivatives of (dx, dy) with respect to (u, v). */
void camera_distortion_partials(float u, float v, const float theta[CAMERA_N_PARAMS], float *dx_u, float *dx_v,
                                float *dy_u, float *dy_v);

/* Measured centroids [px] -> ideal offsets (u', v') = (u - dx, v - dy) [px], n stars. */
void camera_ideal_offsets(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                          float *u_ideal_px, float *v_ideal_px);

/* Ideal offsets [px] -> sensor-frame unit vectors b = (u', v', F) / |.|, b[n][3]. */
void camera_offsets_to_unit(const float *u_ideal_px, const float *v_ideal_px, size_t n, float focal_px,
                            float (*b)[3]);

/* Measured centroids -> sensor-frame unit vectors (what a sensor evaluates every frame). */
void camera_pixels_to_unit(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                           float (*b)[3]);

/* Unit vectors and their analytic Jacobians: b[n][3], j_theta[n][3][10] = db/dtheta (F in px),
 * j_centroid[n][3][2] = db/d(x, y); db/dw = (I - b b^T) / |w| for w = (u', v', F). */
void camera_unit_vector_jacobians(const float *x_px, const float *y_px, size_t n, const float theta[CAMERA_N_PARAMS],
                                  float (*b)[3], float (*j_theta)[3][CAMERA_N_PARAMS], float (*j_centroid)[3][2]);

#endif
