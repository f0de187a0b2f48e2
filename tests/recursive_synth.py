"""Small synthetic star frames for the recursive-estimator tests (not a sky simulator: random directions in the field
of view of a random attitude, through the true camera's inverse mapping, plus Gaussian centroid noise).

Kept independent of ``hostlink.sky`` so the estimator's tests isolate the estimator; the end-to-end replay tests use
the project's simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from crb_bounds import interstar_frame_information

from hostlink.files.params import load_params
from onboard.camera import pixels_to_unit, unit_vector_jacobians
from onboard.interstar import (
    difference_jacobian,
    difference_residuals,
    independent_pairs,
    order_for_pairs,
    pair_covariance,
)
from onboard.params import CameraParams, params_from_dict

#: Seed 004 sec. 3, Table 1 (k signs converted to docs/camera-model.md: k = -k_seed004): the package's seed004_camera.
SEED004_TRUE = load_params("builtin:seed004_camera")
#: The starting values of seed 004's experiments (sec. 3: f 72 mm, principal point (512, 512), no distortion): the
#: package's design nominal (builtin:seed004_nominal, f 70 mm at (511.5, 511.5)) moved further from the truth.
SEED004_PAPER_START = replace(
    load_params("builtin:seed004_nominal"), focal_length_mm=72.0, principal_point_px=(512.0, 512.0)
)


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
    theta = camera.model_vector()
    info = np.zeros((idx.size, idx.size))
    for fr in frames:
        good = ~fr.misidentified
        x, y = fr.x_px[good], fr.y_px[good]
        # evaluate at the noise-free positions would need them; at the measured ones the difference is O(noise)
        info += interstar_frame_information(x, y, theta, noise_px, idx)
    return info


def sky_frames(seed: int, n_frames: int, noise_px: float = 0.05):
    """(true camera, frames as (x, y, r, identified), information (10, 10) at the truth) of a simulated session."""
    from hostlink.sky.references import session_references
    from hostlink.sky.simulate import seed004_config, simulate  # the project's simulator: multi-seed acceptance

    result = simulate(seed004_config(n_frames, seed=seed))
    camera = params_from_dict(result.truth["camera"])
    s = result.session
    r_all = session_references(s).r
    ident = (s.star_id != 0) & np.all(np.isfinite(r_all), axis=1)
    bad = ~ident
    bad[np.array(result.truth["misidentified_rows"], dtype=int)] = True
    theta = camera.model_vector()
    frames = []
    info = np.zeros((10, 10))
    for rows in s.frame_slices():
        frames.append((s.x_px[rows], s.y_px[rows], r_all[rows], ident[rows]))
        keep = ~bad[rows]
        x, y = s.x_px[rows][keep], s.y_px[rows][keep]
        info += interstar_frame_information(x, y, theta, noise_px)
    return camera, frames, info


def synth_frames(seed: int, n_frames: int, noise_px: float = 0.05):
    """Like :func:`sky_frames` for :func:`make_frames` (10-30 stars uniformly on the detector)."""
    frames = make_frames(SEED004_TRUE, n_frames, noise_px, seed=seed)
    info = crb_information(SEED004_TRUE, frames, noise_px, np.arange(10))
    return SEED004_TRUE, [(f.x_px, f.y_px, f.r, f.identified) for f in frames], info


def batch_ml(camera, frames, iterations: int = 3, noise_px: float = 0.05) -> np.ndarray:
    """Reference: the batch maximum-likelihood estimate of the same 2n-3 pair measurements (float64 Gauss-Newton over
    all frames, relinearised at every iteration, started at the truth). Its error is what the data supports; the
    recursive estimate minus this one, over the CRB, is the recursive filter's own excess (a paired comparison, far
    less noisy than the errors themselves: for an estimator of variance (1 + eps) CRB^2, var(T - ML) = eps CRB^2)."""
    theta = camera.model_vector().copy()
    for _ in range(iterations):
        info = np.zeros((10, 10))
        grad = np.zeros(10)
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
            info += h.T @ w[:, :10]
            grad += h.T @ w[:, 10]
        theta = theta + np.linalg.solve(info, grad)  # e = z - h(theta): H dtheta = e (onboard.interstar)
    return theta
