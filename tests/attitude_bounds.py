"""Test helpers for the attitude solvers: the Cramer-Rao covariance of an attitude and the angle between two
attitudes (the yardsticks the solvers are scored with; no production code needs them)."""

from __future__ import annotations

import numpy as np


def attitude_covariance(b: np.ndarray, sigma_rad) -> np.ndarray:
    """Cramer-Rao covariance (3, 3) [rad^2] of the attitude error (small rotation, sensor axes) for unit vectors b
    (N, 3) each with isotropic angular noise sigma_rad (scalar or (N,)): (sum sigma^-2 (I - b b^T))^-1."""
    b = np.asarray(b)
    sig = np.broadcast_to(np.asarray(sigma_rad, dtype=b.dtype), (b.shape[0],))
    info = np.einsum("n,nij->ij", 1 / sig**2, np.eye(3, dtype=b.dtype)[None] - b[:, :, None] * b[:, None, :])
    return np.linalg.inv(info)


def rotation_angle_rad(c_a: np.ndarray, c_b: np.ndarray) -> float:
    """Angle [rad] of the rotation c_a c_b^T (the attitude difference), robust for small angles."""
    d = np.asarray(c_a, dtype=np.float64) @ np.asarray(c_b, dtype=np.float64).T
    skew = np.array([d[1, 2] - d[2, 1], d[2, 0] - d[0, 2], d[0, 1] - d[1, 0]]) / 2
    return float(np.arctan2(np.linalg.norm(skew), (np.trace(d) - 1) / 2))
