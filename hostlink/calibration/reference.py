"""A dense textbook Gauss-Newton / Levenberg-Marquardt solver of the bundle adjustment, kept as the reference the
fast path (:mod:`hostlink.calibration.bundle`) is tested against.

Everything the fast path does cleverly is done plainly here: one stacked residual vector of all stars, one dense
Jacobian over the camera and every frame's rotation increment by central differences (no analytic derivative, no
Schur complement, no chunks, no robust weights, no warm start), and Marquardt's damped normal equations solved as they
stand (Nocedal and Wright, "Numerical Optimization", 2nd ed., sec. 10.3). Its cost grows as the cube of the number of
frames: for sessions of tens of frames only.

The residual is the measurement model's definition (docs/camera-model.md): e = Jc^-1 (q - p), with q the ideal
offsets of the measured centroid, p = F (C r)_xy / (C r)_z the projection of the reference, Jc = I - dD/d(u, v) the
Jacobian of the ideal offsets in the centroid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.frames import apply_attitude_increment, wahba_attitudes
from hostlink.calibration.model import parameter_columns, parameter_scales
from onboard.camera import distortion_partials, ideal_offsets, pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Central-difference step in the scaled unknowns (1 px of each camera parameter's effect, 1 rad of rotation): the
#: truncation error ~h^2 (1e-12 of the derivative) and the rounding error ~1e-16 / h (1e-10) are both far below what
#: moves the minimum by a thousandth of a standard deviation.
FD_STEP = 1e-6
#: Marquardt's damping: start, and factor of growth after a failed step and of shrinking after an accepted one.
START_DAMPING = 1e-3
DAMPING_FACTOR = 10.0
#: A damping this large means no step lowers the cost: the iterate is the minimum to rounding.
MAX_DAMPING = 1e12
#: An accepted step lowering the cost by less than this fraction ends the fit: the rounding of a sum of ~10^3 squares.
COST_TOL = 1e-14


@dataclass
class ReferenceFit:
    theta: np.ndarray  # model vector, all 10 entries
    attitudes: np.ndarray  # (M, 3, 3)
    covariance: np.ndarray  # (K, K) camera block of sigma^2 (J^T J)^-1, model-vector units
    sigma_px: float  # noise per axis from the residuals: sqrt(e^T e / (2 N - K - 3 M))
    iterations: int


def whitened_residuals(data: CalibrationData, theta: np.ndarray, attitudes: np.ndarray) -> np.ndarray:
    """e = Jc^-1 (q - p) of every star, stacked (2 N,) as (e_x0, e_y0, e_x1, ...)."""
    s = np.einsum("nij,nj->ni", np.repeat(attitudes, data.counts, axis=0), data.r)
    p = theta[0] * s[:, :2] / s[:, 2:3]
    q = np.stack(ideal_offsets(data.x_px, data.y_px, theta), axis=1)
    dx_u, dx_v, dy_u, dy_v = distortion_partials(data.x_px - theta[1], data.y_px - theta[2], theta)
    jc = np.stack([np.stack([1 - dx_u, -dx_v], axis=-1), np.stack([-dy_u, 1 - dy_v], axis=-1)], axis=-2)
    return np.linalg.solve(jc, (q - p)[:, :, None])[:, :, 0].ravel()


def reference_fit(
    data: CalibrationData, nominal: CameraParams, estimate: tuple[str, ...] = ESTIMATE_NAMES, max_iter: int = 100
) -> ReferenceFit:
    """Plain least squares over the camera parameters ``estimate`` and every frame's attitude from ``nominal`` and
    the least-squares attitudes through it, by Levenberg-Marquardt on the dense central-difference Jacobian, until
    no step lowers the cost, or one lowers it by less than :data:`COST_TOL`."""
    cols = parameter_columns(estimate)
    scale = parameter_scales(nominal)[cols]
    theta0 = nominal.model_vector(np.float64)
    att0 = wahba_attitudes(pixels_to_unit(data.x_px, data.y_px, theta0), data.r, data.frame_starts)
    k = cols.size

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        theta = theta0.copy()
        theta[cols] += x[:k] * scale
        return theta, apply_attitude_increment(att0, x[k:].reshape(-1, 3))

    def residual(x: np.ndarray) -> np.ndarray:
        return whitened_residuals(data, *unpack(x))

    x = np.zeros(k + 3 * data.n_frames)
    r = residual(x)
    damping = START_DAMPING
    iterations = 0
    while iterations < max_iter:
        iterations += 1
        jac = _jacobian(residual, x)
        a, g = jac.T @ jac, jac.T @ r
        while damping < MAX_DAMPING:
            dx = -np.linalg.solve(a + damping * np.diag(np.diag(a)), g)
            r_new = residual(x + dx)
            if r_new @ r_new < r @ r:
                decrease = 1.0 - (r_new @ r_new) / (r @ r)
                x, r, damping = x + dx, r_new, damping / DAMPING_FACTOR
                break
            damping *= DAMPING_FACTOR
        else:
            break  # no damping lowers the cost: at the minimum
        if decrease < COST_TOL:
            break
    jac = _jacobian(residual, x)
    sigma = float(np.sqrt(r @ r / max(r.size - x.size, 1)))
    cov_scaled = np.linalg.inv(jac.T @ jac)[:k, :k]
    theta, att = unpack(x)
    return ReferenceFit(theta, att, sigma**2 * cov_scaled * np.outer(scale, scale), sigma, iterations)


def _jacobian(residual, x: np.ndarray) -> np.ndarray:
    """d residual / dx by central differences, one column per unknown (:data:`FD_STEP`)."""
    cols = []
    for i in range(x.size):
        step = np.zeros_like(x)
        step[i] = FD_STEP
        cols.append((residual(x + step) - residual(x - step)) / (2.0 * FD_STEP))
    return np.stack(cols, axis=1)
