"""Small synthetic star frames for the recursive-estimator tests (not a sky simulator: random directions in the field
of view of a random attitude, through the true camera's inverse mapping, plus Gaussian centroid noise).

Kept independent of ``hostlink.sky`` so the estimator's tests isolate the estimator; the end-to-end replay tests use
the project's simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.camera import pixels_to_unit
from onboard.interstar import difference_jacobian, independent_pairs, order_for_pairs, pair_covariance
from onboard.params import CameraParams, Distortion

#: Seed 004 sec. 3, Table 1 (k signs converted to CAMERA_MODEL.md: k = -k_seed004).
SEED004_TRUE = CameraParams(70.2262, 12.0, (500.0, 530.0), (1024, 1024), Distortion(k1=-2.0e-10, k2=3.5e-15))
#: What a user knows before calibrating (seed 004 sec. 3: f 72 mm, principal point (512, 512), no distortion).
SEED004_NOMINAL = CameraParams(72.0, 12.0, (512.0, 512.0), (1024, 1024))


@dataclass
class Frame:
    x_px: np.ndarray
    y_px: np.ndarray
    r: np.ndarray  # (N, 3) reference unit vectors
    identified: np.ndarray  # bool
    misidentified: np.ndarray  # bool: r is another star's direction


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def make_frame(
    camera: CameraParams,
    rng: np.random.Generator,
    n_stars: int,
    noise_px: float,
    misid_fraction: float = 0.0,
) -> Frame:
    """One frame: n_stars uniformly on the detector (2 px margin), their true directions rotated to a random
    attitude as references, centroids with N(0, noise_px) per axis. A misidentified star gets the reference of a
    random direction elsewhere in the field (a wrong catalogue star)."""
    w, h = camera.image_size_px
    theta = camera.model_vector()
    x_true = rng.uniform(2.0, w - 3.0, n_stars)
    y_true = rng.uniform(2.0, h - 3.0, n_stars)
    b = pixels_to_unit(x_true, y_true, theta)
    c = _random_rotation(rng)
    r = b @ c  # b = C r  =>  r = C^T b
    mis = rng.random(n_stars) < misid_fraction
    if np.any(mis):
        xo = rng.uniform(2.0, w - 3.0, int(mis.sum()))
        yo = rng.uniform(2.0, h - 3.0, int(mis.sum()))
        r[mis] = pixels_to_unit(xo, yo, theta) @ c
    x = x_true + rng.normal(0.0, noise_px, n_stars)
    y = y_true + rng.normal(0.0, noise_px, n_stars)
    return Frame(x, y, r, np.ones(n_stars, bool), mis)


def make_frames(camera, n_frames, noise_px, min_stars=10, max_stars=30, misid_fraction=0.0, seed=0, focal_mm=None):
    """``n_frames`` frames of min..max stars; ``focal_mm`` (array per frame) overrides the focal length (drift)."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n_frames):
        cam = camera if focal_mm is None else camera.with_focal_length_mm(float(focal_mm[k]))
        n = int(rng.integers(min_stars, max_stars + 1))
        frames.append(make_frame(cam, rng, n, noise_px, misid_fraction))
    return frames


def crb_information(camera: CameraParams, frames, noise_px: float, idx: np.ndarray) -> np.ndarray:
    """Fisher information (K, K), model units (F px), of the interstar difference measurements of ``frames`` at the
    true camera: sum over frames of H^T R^-1 H over the 2n - 3 independent pairs (correctly identified stars only).
    The interstar form eliminates the attitude exactly, so this is the Cramer-Rao bound of the measurement model."""
    from onboard.camera import unit_vector_jacobians

    theta = camera.model_vector()
    info = np.zeros((idx.size, idx.size))
    for fr in frames:
        good = ~fr.misidentified
        x, y = fr.x_px[good], fr.y_px[good]
        # evaluate at the noise-free positions would need them; at the measured ones the difference is O(noise)
        o = order_for_pairs(x, y)
        b, jt, jc = unit_vector_jacobians(x[o], y[o], theta)
        i, j = independent_pairs(o.size)
        hh = difference_jacobian(b, jt[:, :, idx], i, j)
        r = pair_covariance(b, jc, i, j, noise_px)
        info += hh.T @ np.linalg.solve(r, hh)
    return info
