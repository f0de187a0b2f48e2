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


def per_frame_products(
    terms: np.ndarray, right: np.ndarray, weights: np.ndarray, frame_starts: np.ndarray
) -> np.ndarray:
    """sum_k w_k T_k^T R_k over the stars k of each frame, (M, c, d), for per-star matrices T_k (N, r, c) and
    R_k (N, r, d) (here r = 2 residual rows; T the Jacobian columns and the residual, R the attitude columns).

    Frames are laid out padded with zeros to the largest star count, so the sums are one batched matrix product
    per frame (r x nmax rows) instead of one per star; padding adds exact zeros, so every frame's sum is its own
    whatever the other frames of the call (to the rounding of the product's blocking)."""
    m = frame_starts.shape[0] - 1
    counts = np.diff(frame_starts)
    n, r, c = terms.shape
    d = right.shape[2]
    nmax = int(counts.max(initial=0))
    # row k of frame f goes to slot k - start_f of that frame: flat position f * nmax + k - start_f
    flat = np.arange(n) + np.repeat(np.arange(m) * nmax - frame_starts[:-1], counts)
    padded = np.zeros((m * nmax, r * c))
    padded[flat] = terms.reshape(n, r * c)
    padded_r = np.zeros((m * nmax, r * d))
    padded_r[flat] = (right * weights[:, None, None]).reshape(n, r * d)
    return padded.reshape(m, nmax * r, c).transpose(0, 2, 1) @ padded_r.reshape(m, nmax * r, d)


def triad_attitudes(b: np.ndarray, r: np.ndarray, frame_starts: np.ndarray) -> np.ndarray:
    """A closed-form attitude per frame (M, 3, 3), b ~ C r, by TRIAD (Black 1964; Shuster and Oh 1981, sec. II):
    the primary pair is the frame's mean direction (exact under a rotation), the secondary its star farthest from
    that mean (the longest lever arm for the roll). No SVD: a start for Gauss-Newton, within a few centroid-noise
    angles over the pair's separation of the least-squares attitude."""
    counts = np.diff(frame_starts)
    m = counts.shape[0]
    frame = np.repeat(np.arange(m), counts)
    b1 = np.add.reduceat(b, frame_starts[:-1], axis=0)
    r1 = np.add.reduceat(r, frame_starts[:-1], axis=0)
    cos_to_mean = np.einsum("ni,ni->n", b, b1[frame]) / np.linalg.norm(b1, axis=1)[frame]
    slot = np.arange(b.shape[0]) - frame_starts[:-1][frame]
    padded = np.full((m, int(counts.max(initial=1))), np.inf)
    padded[frame, slot] = cos_to_mean
    far = frame_starts[:-1] + np.argmin(padded, axis=1)  # per frame, the star with the smallest cosine to the mean
    return _triad_matrix(b1, b[far]) @ _triad_matrix(r1, r[far]).transpose(0, 2, 1)


def _triad_matrix(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """Columns (v1, v1 x v2, v1 x (v1 x v2)), normalised: the TRIAD frame of a vector pair, (M, 3, 3)."""
    t1 = v1 / np.linalg.norm(v1, axis=1, keepdims=True)
    t2 = _cross(t1, v2)
    t2 /= np.linalg.norm(t2, axis=1, keepdims=True)
    return np.stack([t1, t2, _cross(t1, t2)], axis=2)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for stacks of 3-vectors (M, 3): np.cross's products and differences written out (the same numbers,
    without its axis handling, which costs more than the arithmetic for a few hundred vectors)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out
