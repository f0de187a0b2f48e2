"""The judge of a calibration: the Cramer-Rao bound of a session, the validation residual it bounds, and the
Cramer-Rao covariance of an attitude. Scoring a calibration against a known truth (a simulated session, a camera
measured on a test bench) is something users do; the test suite and the benchmarks use these same functions.

Fisher information. Each identified star is a measured centroid c = (x, y) with isotropic Gaussian noise sigma
per axis around c(theta, phi_f), the point where the true camera images the star (c solves
q(c; theta) = F (C_f r)_xy / (C_f r)_z). By the implicit-function theorem dc = -Jc^-1 d(q - p), so the
information of the whole session over (camera, every attitude) is J^T J / sigma^2 with J the Jacobian of the
whitened residual of the bundle's measurement model (``hostlink.calibration.bundle``) evaluated at the truth and at
the noise-free centroids. The attitudes are nuisance parameters: the camera's information is the Schur complement

    I_theta = (U - sum_f B_f A_f^-1 B_f^T) / sigma^2,

and any unbiased estimator has Cov(theta_hat) >= I_theta^-1 (Kay 1993, ch. 3). The test suite checks this
information against finite differences of the forward simulator ``onboard.camera.unit_to_pixels``, an independent
route.

Validation residual (what "accuracy" means in the acceptance tests and benchmarks). Over a G x G grid of measured
pixel positions spanning the detector, map each point to a direction with the estimated and with the true camera,
rotate the estimated directions by the rotation that best aligns them (a common rotation is absorbed by the attitude
and is not a calibration error), project both onto the true ideal image plane, P(b) = F_true (b_x / b_z, b_y / b_z),
and take the RMS length of the difference [px]:

    V(theta_hat) = sqrt( mean_g |P(R b_hat_g) - P(b_g)|^2 ),   R = argmin of the same sum.

To first order V^2 = |G_perp (theta_hat - theta)|^2 / n_grid with G_perp the grid Jacobian with its three rotation
directions projected out, so the bound on E[V^2] is trace(G_perp I_theta^-1 G_perp^T) / n_grid. The
principal-point/attitude degeneracy does not inflate V: what the attitude absorbs is projected out of both.

Interstar form (the onboard estimator's measurement model, ``onboard.interstar``): the 2n - 3 independent pair
differences of a frame eliminate its attitude exactly, so their information summed over frames is the Cramer-Rao
bound of that model (:func:`interstar_frame_information`, :func:`interstar_information`); :func:`interstar_batch_ml`
is the batch maximum-likelihood estimate of the same measurements, the reference a recursive estimate is compared
with.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hostlink.calibration.bundle import accumulate_normals, reduced_normal
from hostlink.calibration.data import CalibrationData
from hostlink.calibration.frames import rotation_from_vector, skew, wahba_attitudes
from onboard.camera import pixels_to_unit, unit_vector_jacobians
from onboard.interstar import (
    difference_jacobian,
    difference_residuals,
    independent_pairs,
    order_for_pairs,
    pair_covariance,
)
from onboard.params import CameraParams

#: Default validation grid: 21 x 21 points over the detector, corners included.
GRID_SIDE = 21


def fisher_information(
    data_noise_free: CalibrationData,
    theta_true: np.ndarray,
    attitudes_true: np.ndarray,
    cols: np.ndarray,
    sigma_px: float,
) -> np.ndarray:
    """Camera Fisher information (K, K) with the per-frame attitudes eliminated (Schur complement), in model-vector
    units, for centroid noise ``sigma_px`` per axis. ``data_noise_free`` holds the true (noise-free) centroids."""
    ones = np.ones(data_noise_free.n_obs)
    blocks = accumulate_normals(data_noise_free, theta_true, attitudes_true, cols, ones, np.ones(cols.size))
    return reduced_normal(blocks, 0.0)[0] / sigma_px**2


def grid_points(params: CameraParams, side: int = GRID_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """side x side measured-pixel positions spanning the detector, corners included (docs/camera-model.md extent)."""
    w, h = params.image_size_px
    gx, gy = np.meshgrid(np.linspace(-0.5, w - 0.5, side), np.linspace(-0.5, h - 0.5, side))
    return gx.ravel(), gy.ravel()


def _project(b: np.ndarray, focal_px: float) -> np.ndarray:
    return focal_px * b[:, :2] / b[:, 2:3]


def _project_jacobian(b: np.ndarray, focal_px: float) -> np.ndarray:
    """dP/db (n, 2, 3) for P(b) = F (b_x / b_z, b_y / b_z)."""
    n = b.shape[0]
    j = np.zeros((n, 2, 3))
    j[:, 0, 0] = focal_px / b[:, 2]
    j[:, 1, 1] = focal_px / b[:, 2]
    j[:, :, 2] = -focal_px * b[:, :2] / b[:, 2:3] ** 2
    return j


#: Gauss-Newton steps refining the grid alignment from the Wahba rotation (the least-squares rotation of the
#: directions, already close to the one of the pixel metric); the number the suite's scores were measured with.
ALIGN_STEPS = 5


def validation_residual_px(
    theta_est: np.ndarray, params_true: CameraParams, side: int = GRID_SIDE, return_field: bool = False
):
    """V(theta_hat) of the module docstring [px] (and, if asked, the (n_grid, 2) difference field)."""
    gx, gy = grid_points(params_true, side)
    b_est = pixels_to_unit(gx, gy, np.asarray(theta_est, dtype=np.float64))
    return validation_residual_from_directions_px(b_est, params_true, side, return_field)


def validation_residual_from_directions_px(
    b_est: np.ndarray, params_true: CameraParams, side: int = GRID_SIDE, return_field: bool = False
):
    """V of the module docstring [px] for any camera model: ``b_est`` (n_grid, 3) are the directions it gives the
    points of :func:`grid_points` (e.g. another library's undistortion of them).

    The alignment starts from the least-squares (Wahba) rotation and is refined by Gauss-Newton on the pixel metric,
    so it minimises exactly the quantity reported."""
    theta_true = params_true.model_vector(np.float64)
    gx, gy = grid_points(params_true, side)
    b_true = pixels_to_unit(gx, gy, theta_true)
    rot = wahba_attitudes(b_true, b_est, np.array([0, gx.size]))[0]  # b_true ~ rot b_est
    target = _project(b_true, theta_true[0])
    for _ in range(ALIGN_STEPS):
        s = b_est @ rot.T
        d = _project(s, theta_true[0]) - target
        j = (_project_jacobian(s, theta_true[0]) @ skew(s)).reshape(-1, 3)
        step = np.linalg.lstsq(j, -d.ravel(), rcond=None)[0]
        rot = rotation_from_vector(-step) @ rot
    diff = _project(b_est @ rot.T, theta_true[0]) - target
    v = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1))))
    return (v, diff) if return_field else v


def validation_jacobian(params_true: CameraParams, cols: np.ndarray, side: int = GRID_SIDE) -> np.ndarray:
    """G_perp (2 n_grid, K): first-order change of the grid difference field per unit change of the model-vector
    entries ``cols``, with the rotation directions projected out."""
    theta = params_true.model_vector(np.float64)
    gx, gy = grid_points(params_true, side)
    b, jb_theta, _ = unit_vector_jacobians(gx, gy, theta)
    jp = _project_jacobian(b, theta[0])
    g_theta = (jp @ jb_theta[:, :, cols]).reshape(-1, cols.size)
    g_rot = (jp @ skew(b)).reshape(-1, 3)
    q, _ = np.linalg.qr(g_rot)
    return g_theta - q @ (q.T @ g_theta)


def crb_validation_px(information: np.ndarray, g_perp: np.ndarray) -> float:
    """sqrt(trace(G_perp I^-1 G_perp^T) / n_grid): the Cramer-Rao bound on the RMS validation residual [px]."""
    n_grid = g_perp.shape[0] // 2
    d = np.sqrt(np.diag(information))
    inv = np.linalg.pinv(information / d[:, None] / d[None, :], rcond=1e-15, hermitian=True) / d[:, None] / d[None, :]
    return float(np.sqrt(np.trace(g_perp @ inv @ g_perp.T) / n_grid))


def interstar_frame_information(
    x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray, noise_px: float, cols: np.ndarray | None = None
) -> np.ndarray:
    """Fisher information (K, K), model units (F in px), of one frame's difference-form interstar measurements at
    ``theta``: H^T R^-1 H over its 2n - 3 independent pairs (``onboard.interstar``), R from centroid noise
    ``noise_px``. The interstar form eliminates the attitude exactly, so summed over frames this is the Cramer-Rao
    bound of the onboard estimator's measurement model. ``cols`` selects parameters (default all ten)."""
    cols = np.arange(theta.shape[0]) if cols is None else np.asarray(cols)
    if x_px.shape[0] < 3:
        return np.zeros((cols.size, cols.size))
    o = order_for_pairs(x_px, y_px)
    b, jt, jc = unit_vector_jacobians(x_px[o], y_px[o], theta)
    i, j = independent_pairs(o.size)
    h = difference_jacobian(b, jt[:, :, cols], i, j)
    return h.T @ np.linalg.solve(pair_covariance(b, jc, i, j, noise_px), h)


def interstar_information(
    camera: CameraParams, frames: Sequence, noise_px: float, cols: np.ndarray | None = None
) -> np.ndarray:
    """Fisher information (K, K), model units (F px), of the interstar difference measurements of ``frames`` (each
    with ``x_px, y_px, misidentified``, as :class:`hostlink.calibration.synthetic.Frame`) at the true camera: the
    sum over frames of :func:`interstar_frame_information` over the correctly identified stars. Evaluated at the
    measured centroids (the noise-free ones are not needed: the difference is O(noise) relative)."""
    theta = camera.model_vector()
    cols = np.arange(theta.shape[0]) if cols is None else np.asarray(cols)
    info = np.zeros((cols.size, cols.size))
    for fr in frames:
        good = ~fr.misidentified
        info += interstar_frame_information(fr.x_px[good], fr.y_px[good], theta, noise_px, cols)
    return info


#: Gauss-Newton relinearisations of :func:`interstar_batch_ml`, started at the truth; the number the recursive
#: estimator's paired comparisons were measured with.
ML_ITERATIONS = 3


def interstar_batch_ml(
    camera: CameraParams, frames: Sequence, iterations: int = ML_ITERATIONS, noise_px: float = 0.05
) -> np.ndarray:
    """The batch maximum-likelihood estimate (10,) of the 2n - 3 pair measurements of ``frames`` (each a tuple
    ``(x_px, y_px, r, identified)``): float64 Gauss-Newton over all frames, relinearised at every iteration,
    started at the truth. Its error is what the data supports; a recursive estimate minus this one, over the CRB,
    is the recursive filter's own excess (a paired comparison, far less noisy than the errors themselves: for an
    estimator of variance (1 + eps) CRB^2, var(T - ML) = eps CRB^2)."""
    theta = camera.model_vector().copy()
    k = theta.shape[0]
    for _ in range(iterations):
        info = np.zeros((k, k))
        grad = np.zeros(k)
        for x, y, r, ok in frames:
            x, y, r = x[ok], y[ok], r[ok]
            if x.size < 3:
                continue
            o = order_for_pairs(x, y)
            b, jt, jc = unit_vector_jacobians(x[o], y[o], theta)
            i, j = independent_pairs(o.size)
            h = difference_jacobian(b, jt, i, j)
            e = difference_residuals(b, r[o], i, j)
            w = np.linalg.solve(pair_covariance(b, jc, i, j, noise_px), np.column_stack([h, e]))
            info += h.T @ w[:, :k]
            grad += h.T @ w[:, k]
        theta = theta + np.linalg.solve(info, grad)  # e = z - h(theta): H dtheta = e (onboard.interstar)
    return theta


def attitude_covariance(b: np.ndarray, sigma_rad) -> np.ndarray:
    """Cramer-Rao covariance (3, 3) [rad^2] of the attitude error (small rotation, sensor axes) for unit vectors b
    (N, 3) each with isotropic angular noise sigma_rad (scalar or (N,)): (sum sigma^-2 (I - b b^T))^-1
    (Shuster and Oh 1981, the QUEST measurement model)."""
    b = np.asarray(b)
    sig = np.broadcast_to(np.asarray(sigma_rad, dtype=b.dtype), (b.shape[0],))
    info = np.einsum("n,nij->ij", 1 / sig**2, np.eye(3, dtype=b.dtype)[None] - b[:, :, None] * b[:, None, :])
    return np.linalg.inv(info)


def rotation_angle_rad(c_a: np.ndarray, c_b: np.ndarray) -> float:
    """Angle [rad] of the rotation c_a c_b^T (the attitude difference), robust for small angles."""
    d = np.asarray(c_a, dtype=np.float64) @ np.asarray(c_b, dtype=np.float64).T
    axis = np.array([d[1, 2] - d[2, 1], d[2, 0] - d[0, 2], d[0, 1] - d[1, 0]]) / 2
    return float(np.arctan2(np.linalg.norm(axis), (np.trace(d) - 1) / 2))
