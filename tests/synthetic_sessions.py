"""Random star fields seen through a known camera, for tests and benchmarks of the calibration.

Not the sky simulator (``hostlink.sky.simulate`` observes the real Hipparcos sky): here star positions are drawn
uniformly over the detector, their directions come from the camera model (``onboard.camera.pixels_to_unit``) and a
random attitude, so the truth is exact by construction and any number of frames is cheap. Misidentified stars get
the reference direction of another point of the same field (the hard case: plausible angles, wrong star).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData, build_data
from hostlink.sky.simulate import random_rotations
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams


@dataclass(frozen=True)
class SyntheticSession:
    data: CalibrationData
    params_true: CameraParams
    attitudes_true: np.ndarray  # (M, 3, 3), b = C r
    x_true_px: np.ndarray  # noise-free centroids (N,)
    y_true_px: np.ndarray
    misidentified: np.ndarray  # (N,) bool
    noise_px: float


def synthetic_session(
    params: CameraParams,
    n_frames: int,
    stars_per_frame: tuple[int, int] = (10, 30),
    noise_px: float = 0.05,
    misidentified_fraction: float = 0.0,
    seed: int = 0,
    margin_px: float = 2.0,
) -> SyntheticSession:
    """Draw ``n_frames`` frames of uniformly placed stars (count uniform in ``stars_per_frame``, inclusive), with
    isotropic Gaussian centroid noise ``noise_px`` per axis and a fraction of misidentified stars."""
    rng = np.random.default_rng(seed)
    width, height = params.image_size_px
    counts = rng.integers(stars_per_frame[0], stars_per_frame[1] + 1, size=n_frames)
    n = int(counts.sum())
    frame_key = np.repeat(np.arange(n_frames), counts)
    x_true = rng.uniform(margin_px - 0.5, width - 0.5 - margin_px, n)
    y_true = rng.uniform(margin_px - 0.5, height - 0.5 - margin_px, n)
    theta = params.model_vector(np.float64)
    b = pixels_to_unit(x_true, y_true, theta)
    att = random_rotations(rng, n_frames)
    r = np.einsum("nji,nj->ni", att[frame_key], b)  # r = C^T b
    wrong = rng.random(n) < misidentified_fraction
    if np.any(wrong):
        xw = rng.uniform(-0.5, width - 0.5, int(wrong.sum()))
        yw = rng.uniform(-0.5, height - 0.5, int(wrong.sum()))
        bw = pixels_to_unit(xw, yw, theta)
        r[wrong] = np.einsum("nji,nj->ni", att[frame_key[wrong]], bw)
    x = x_true + rng.normal(scale=noise_px, size=n)
    y = y_true + rng.normal(scale=noise_px, size=n)
    star_id = np.arange(1, n + 1)
    data = build_data(x, y, r, frame_key, star_id=star_id)
    return SyntheticSession(data, params, att, x_true, y_true, wrong, noise_px)
