"""Per-frame helpers, vectorised over frames: the SVD attitude fit and small-rotation updates.

The attitude of every frame at once: the profile matrices B = sum_k w_k b_k r_k^T are accumulated per frame here and
solved by ``onboard.attitude.rotation_from_profile`` (Markley 1988), the same formula the sensor uses, so b = C r
as in CAMERA_MODEL.md.
"""

from __future__ import annotations

import numpy as np

from hostlink.calibration.data import frame_chunks
from onboard.attitude import rotation_from_profile


def wahba_svd(b: np.ndarray, r: np.ndarray, frame_starts: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares attitude per frame, (M, 3, 3), with b_k ~ C r_k (Markley's SVD method).

    b, r: (N, 3) unit vectors grouped by frame; weights (N,) >= 0 (default 1). A frame whose weighted stars do
    not fix a rotation (fewer than two non-parallel) gets the best rotation the SVD offers (not unique).
    """
    m = frame_starts.shape[0] - 1
    big_b = np.zeros((m, 3, 3))
    for f0, f1 in frame_chunks(frame_starts, 50_000):  # bounded working memory: (rows, 3, 3) per chunk
        a, z = int(frame_starts[f0]), int(frame_starts[f1])
        outer = b[a:z, :, None] * r[a:z, None, :]
        if weights is not None:
            outer = outer * weights[a:z, None, None]
        local = frame_starts[f0:f1] - a
        nonempty = np.diff(frame_starts[f0 : f1 + 1]) > 0
        if np.any(nonempty):
            big_b[f0:f1][nonempty] = np.add.reduceat(outer, local[nonempty], axis=0)
    return rotation_from_profile(big_b)[0]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v x], shape (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def rotation_from_vector(a: np.ndarray) -> np.ndarray:
    """exp([a x]) by Rodrigues' formula, for rotation vectors a (..., 3) [rad]; shape (..., 3, 3)."""
    angle = np.sqrt(np.sum(a * a, axis=-1))
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    # series limits below 1e-8 rad, where sin(x)/x and (1 - cos x)/x^2 equal 1 and 1/2 to double precision
    s = np.where(small, 1.0, np.sin(safe) / safe)
    c = np.where(small, 0.5, (1.0 - np.cos(safe)) / (safe * safe))
    k = skew(a)
    return np.eye(3) + s[..., None, None] * k + c[..., None, None] * (k @ k)


def apply_attitude_increment(attitude: np.ndarray, dphi: np.ndarray) -> np.ndarray:
    """C <- exp(-[dphi x]) C: the update whose first-order effect on s = C r is ds = [s x] dphi."""
    return rotation_from_vector(-dphi) @ attitude
