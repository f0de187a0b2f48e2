"""Geodesic acceleration of a Gauss-Newton step (Transtrum and Sethna 2012), measured on a sample of the frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.frames import apply_attitude_increment
from hostlink.calibration.model import residual_lengths, residuals
from hostlink.calibration.normal import accumulate_normals, reduced_normal, solve_scaled
from hostlink.calibration.passes import frame_attitudes, robust_weights

#: Geodesic acceleration of a Gauss-Newton step over the full data (:func:`step_acceleration`) for steps above this
#: many standard deviations (below, what the second-order term leaves is below ~0.01 sigma and the contraction test
#: ends the fit on it anyway).
ACCELERATION_MIN_SIGMAS = 1.0


#: The acceleration is used only while 2 |a| / |v| (in the camera's standard deviations) is at most this: Transtrum
#: and Sethna's bound (2012, sec. 3.2), beyond which the second-order model of the step is not to be trusted.
ACCELERATION_MAX_RATIO = 0.75


#: The step fraction h of the second difference (r(+h v) - 2 r(0) + r(-h v)) / h^2 along the step: exact for the
#: quadratic term, the quartic one entering as h^2 / 12 of it.
ACCELERATION_H = 0.5


def step_acceleration(
    sample: CalibrationData,
    theta: np.ndarray,
    dx: np.ndarray,
    cols: np.ndarray,
    col_scale: np.ndarray,
    sigma_px: float,
    huber_k: float,
    s_full: np.ndarray,
    n_obs_full: int,
) -> np.ndarray | None:
    """The geodesic acceleration a (scaled columns) of the Gauss-Newton step ``dx`` of the full data at the camera
    ``theta`` (Transtrum and Sethna 2012, "Improvements to the Levenberg-Marquardt algorithm for nonlinear
    least-squares minimization", eq. 15: a = -(J^T W J)^-1 J^T W r''; the step taken is dx + a / 2), its
    second-order term measured on ``sample`` (frames of the same session held in memory): the second directional
    derivative r'' of each star's residual along the joint step (the camera's ``dx`` and each frame's attitude step
    that goes with it, -A^-1 (B^T dx + g_phi)) by the central second difference at :data:`ACCELERATION_H`, which is
    free of the centroid noise (it cancels); J^T W r'' reduced over the sample's attitudes (Schur complement) and
    scaled to the full data by their ratio of stars, then solved with the full data's reduced matrix ``s_full``.

    What it corrects: a principal point d px off is compensated by every frame's attitude, whose rotation adds a
    second-order change of scale, ~0.9 d^2 / F (measured: the focal length a Gauss-Newton step leaves), and the
    distortion's curvature in the principal point adds its own; along the weak principal-point direction these are
    several tenths of the camera's standard deviation (what one step leaves with and without it:
    docs/calibration.md). None when the sample's terms are not finite."""
    with np.errstate(all="ignore"):
        att = frame_attitudes(sample, theta, sigma_px, huber_k)
        e0 = residuals(sample, theta, att)
        if sample.sigma_px is None:
            w = robust_weights(residual_lengths(e0), sigma_px, huber_k)
        else:  # the whitening by each star's noise as a weight 1 / sigma_k^2 on the raw terms
            inv = 1.0 / sample.sigma_px
            w = robust_weights(residual_lengths(e0) * inv, sigma_px, huber_k) * inv * inv
        blocks = accumulate_normals(sample, theta, att, cols, w, col_scale)
        try:
            _, _, a_inv = reduced_normal(blocks)
        except np.linalg.LinAlgError:
            return None
        dphi = -np.einsum("mij,mj->mi", a_inv, np.einsum("mkj,k->mj", blocks.b, dx) + blocks.g_phi)

        def moved(h: float) -> np.ndarray:
            camera = theta.copy()
            camera[cols] += h * dx * col_scale
            return residuals(sample, camera, apply_attitude_increment(att, h * dphi))

        h = ACCELERATION_H
        r2 = (moved(h) - 2.0 * e0 + moved(-h)) / (h * h)
        curvature = accumulate_normals(sample, theta, att, cols, w, col_scale, values=r2)
        _, rhs, _ = reduced_normal(replace(blocks, g=curvature.g, g_phi=curvature.g_phi))
        accel = solve_scaled(s_full, rhs * (n_obs_full / max(sample.n_obs, 1)))
    return accel if np.all(np.isfinite(accel)) else None
