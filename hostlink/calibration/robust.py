"""Robustness against misidentified stars and false matches: interstar voting, Huber weights, residual gating.

1. Voting (before any fit): interstar angles are invariant under the unknown attitude (seed 000 eq. 3), so a star
   whose angles to most other stars of its frame disagree with the catalogue's is misidentified. The tolerance is
   generous enough for an uncalibrated nominal camera (a relative focal-length error plus a few pixels).
2. Huber loss during the fit (IRLS weights), so what voting missed cannot pull the solution far.
3. Gating after convergence: residuals beyond ``gate`` robust sigmas are dropped and the fit is repeated.
"""

from __future__ import annotations

import math

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks, padded_frames, pair_angles_rad

#: median |e| of a 2-D isotropic Gaussian with unit sigma per axis (Rayleigh median sqrt(2 ln 2)).
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


def vote_consistent_stars(
    data: CalibrationData,
    b: np.ndarray,
    rel_tol: float = 0.03,
    abs_tol_rad: float = 1e-3,
    min_agreement: float = 0.5,
    chunk_obs: int = 20_000,
) -> np.ndarray:
    """(N,) bool: stars whose interstar angles agree with the catalogue for at least ``min_agreement`` of the other
    stars of their frame. ``b`` are measured directions from the nominal camera.

    A pair agrees when |angle_b - angle_r| <= rel_tol * angle_r + abs_tol_rad (defaults: a nominal focal length
    within 3 %, and 1 mrad for principal-point and distortion errors of a few pixels at typical focal lengths).
    Frames are padded to their largest star count within a chunk, so the work is vectorised and bounded.
    """
    keep = np.zeros(data.n_obs, dtype=bool)
    starts = data.frame_starts
    for f0, f1 in frame_chunks(starts, chunk_obs):
        pf = padded_frames(data, b, f0, f1)
        nmax = pf.valid.shape[1]
        if nmax < 2:
            continue
        valid, rows, frame_local, slot = pf.valid, pf.rows, pf.frame, pf.slot
        ang_b = pair_angles_rad(pf.b)
        ang_r = pair_angles_rad(pf.r)
        pair_ok = valid[:, :, None] & valid[:, None, :]
        pair_ok &= ~np.eye(nmax, dtype=bool)[None]
        agree = (np.abs(ang_b - ang_r) <= rel_tol * ang_r + abs_tol_rad) & pair_ok
        others = np.maximum(pair_ok.sum(axis=2), 1)
        frac = agree.sum(axis=2) / others
        keep[rows] = frac[frame_local, slot] >= min_agreement
    return keep


def robust_sigma_2d(residual_norm: np.ndarray) -> float:
    """Per-axis sigma from norms of 2-D residuals: median / sqrt(2 ln 2) (50 % breakdown, exact for Gaussians)."""
    if residual_norm.size == 0:
        return float("nan")
    return float(np.median(residual_norm) / RAYLEIGH_MEDIAN)


def huber_weights(residual_norm: np.ndarray, scale: float, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss on the norm of a residual: 1 inside k * scale, k * scale / |e| outside."""
    z = residual_norm / (k * scale)
    return np.where(z <= 1.0, 1.0, 1.0 / np.maximum(z, 1e-300))


def huber_cost(residual_norm: np.ndarray, scale: float, k: float, weights: np.ndarray | None = None) -> float:
    """sum rho(|e|) with rho(t) = t^2 / 2 inside c = k * scale and c |t| - c^2 / 2 outside (Huber 1964)."""
    c = k * scale
    t = residual_norm
    rho = np.where(t <= c, 0.5 * t * t, c * t - 0.5 * c * c)
    if weights is not None:
        rho = rho * weights
    return float(np.sum(rho))
