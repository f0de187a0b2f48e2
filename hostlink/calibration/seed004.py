"""Seed 004's three-step calibration (Ye and Yang 2017, sec. 2).

1. Distortion ignored: Levenberg-Marquardt on (x0, y0, f) with the cosine objective (eq. 1-5).
2. With that (x0, y0, f) taken as exact: linear least squares for the radial k1, k2 (eq. 6-10). The ideal point
   x_hat of eq. 6 is where the distortion-free camera images the catalogue star; the attitude it needs comes from
   the step-1 camera (a least-squares fit per frame: Markley's solution of the same Wahba problem the paper solves
   by QUEST).
   The project's convention evaluates the distortion at the measured point (docs/camera-model.md: k = -k_seed004),
   so eq. 6 reads q(x_d; x0, y0, k) = x_hat - x0 with q linear in (k1, k2): its columns are the camera model's
   dq/dk (``onboard.camera.ideal_offset_jacobians``).
3. Levenberg-Marquardt on all parameters (x0, y0, f, k1, k2) with the cosine objective (eq. 11-13).

The paper's Table 2 compares these stages: group 1 (least squares, step 1 alone), group 2 (Samaan: optical, then
distortion with the optical parameters held) and group 3 (all three steps). ``stages`` keeps each of them.
The interstar rows are the 2n - 3 independent pairs whitened by their covariance (see ``interstar_methods``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.frames import wahba_attitudes
from hostlink.calibration.interstar_methods import InterstarFit, fit_interstar, frame_pair_orders
from onboard.camera import ideal_offset_jacobians, pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams

#: The parameters seed 004 estimates (only the radial k1, k2 of the distortion).
SEED004_ESTIMATE = ("f", "x0", "y0", "k1", "k2")


def radial_least_squares(data: CalibrationData, theta: np.ndarray) -> np.ndarray:
    """Step 2 (seed 004 eq. 6-10): (k1, k2) by linear least squares with (F, x0, y0) of ``theta`` held exact.

    Returns theta with k1, k2 replaced (other distortion terms unchanged)."""
    theta0 = theta.copy()
    theta0[3:5] = 0.0
    att = wahba_attitudes(pixels_to_unit(data.x_px, data.y_px, theta0), data.r, data.frame_starts)
    s = np.einsum("nij,nj->ni", np.repeat(att, data.counts, axis=0), data.r)
    x_hat = theta0[0] * s[:, :2] / s[:, 2:3]  # ideal offsets of the catalogue stars (eq. 6 right-hand side)
    q0, jq, _ = ideal_offset_jacobians(data.x_px, data.y_px, theta0)
    design = jq[:, :, 3:5].reshape(-1, 2)  # S of eq. 8 in this project's sign convention
    target = (x_hat - q0).ravel()  # t of eq. 9
    col = np.linalg.norm(design, axis=0)
    k = np.linalg.lstsq(design / col, target, rcond=None)[0] / col  # eq. 10, column-equilibrated
    out = theta.copy()
    out[3:5] = k
    return out


def calibrate_seed004(
    data: CalibrationData,
    nominal: CameraParams,
    estimate: tuple[str, ...] = SEED004_ESTIMATE,
    progress: Callable[[dict], None] | None = None,
) -> InterstarFit:
    """The three steps; ``estimate`` is the parameter set of step 3 (default the paper's five)."""
    orders = frame_pair_orders(data)
    history: list[dict] = []
    stages: list[dict] = []
    nominal_theta = nominal.model_vector(np.float64)
    held = np.array([n not in estimate for n in ESTIMATE_NAMES])
    theta = np.where(held, nominal_theta, 0.0)  # the paper's start: no distortion (parameters held stay nominal)
    theta[:3] = nominal_theta[:3]
    optical = tuple(n for n in ("f", "x0", "y0") if n in estimate)
    theta = fit_interstar(
        data,
        theta,
        nominal,
        optical,
        "cos",
        orders,
        levenberg_marquardt=True,
        history=history,
        label="step 1: LM (x0, y0, f)",
        progress=progress,
    )[0]
    stages.append({"name": "step 1 (least squares, Table 2 group 1)", "theta": theta.copy()})
    if "k1" in estimate or "k2" in estimate:
        theta = np.where(held, nominal_theta, radial_least_squares(data, theta))  # (k1, k2) together
    stages.append({"name": "step 2 (optical then radial, Table 2 group 2)", "theta": theta.copy()})
    final = tuple(n for n in ESTIMATE_NAMES if n in estimate)
    theta, normal, cost, n_pairs = fit_interstar(
        data,
        theta,
        nominal,
        final,
        "cos",
        orders,
        levenberg_marquardt=True,
        history=history,
        label="step 3: LM (all)",
        progress=progress,
    )
    stages.append({"name": "step 3 (all parameters, Table 2 group 3)", "theta": theta.copy()})
    dof = max(n_pairs - len(final), 1)
    return InterstarFit(
        theta=theta,
        estimate=final,
        normal=normal,
        sigma_estimated_px=float(np.sqrt(cost / dof)),
        history=history,
        stages=stages,
    )
