"""Synthetic star fields seen through a known camera, with their exact truth: what tests, benchmarks and users
scoring a calibration method (``hostlink.calibration.crb``) generate data with.

Not the sky simulator (``hostlink.sky.simulate`` observes the real Hipparcos sky): here star positions are drawn
uniformly over the detector, their directions come from the camera model (``onboard.camera.pixels_to_unit``) and a
random attitude (uniform over SO(3), ``hostlink.sky.simulate.random_rotations``), so the truth is exact by
construction and any number of frames is cheap. Misidentified stars get the reference direction of another point of
the same field (the hard case: plausible angles, wrong star).

Two forms: :func:`synthetic_session` gives the calibration's arrays (:class:`CalibrationData`) of a whole session;
:func:`make_frames` gives frame by frame what the onboard recursive estimator takes (and, with ``focal_mm``, a
drifting focal length). :func:`sky_frames` is the same frame form for a session of the real-sky simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hostlink.calibration.crb import interstar_frame_information, interstar_information
from hostlink.calibration.data import CalibrationData, build_data
from hostlink.files.params import load_params
from hostlink.sky.simulate import random_rotations
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, params_from_dict


@dataclass(frozen=True)
class SyntheticSession:
    data: CalibrationData
    params_true: CameraParams
    attitudes_true: np.ndarray  # (M, 3, 3), b = C r
    x_true_px: np.ndarray  # noise-free centroids (N,)
    y_true_px: np.ndarray
    misidentified: np.ndarray  # (N,) bool
    noise_px: float

    def noise_free_data(self) -> CalibrationData:
        """The correctly identified stars at their noise-free centroids: what the Fisher information of the session
        is evaluated on (``hostlink.calibration.crb.fisher_information``)."""
        good = ~self.misidentified
        d = self.data
        return build_data(self.x_true_px[good], self.y_true_px[good], d.r[good], d.frame_index()[good])


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


def seed004_true_camera() -> CameraParams:
    """Seed 004 sec. 3, Table 1 (k signs converted to docs/camera-model.md: k = -k_seed004): the package's
    ``builtin:seed004_camera``."""
    return load_params("builtin:seed004_camera")


def seed004_paper_start() -> CameraParams:
    """The starting values of seed 004's experiments (sec. 3: f 72 mm, principal point (512, 512), no distortion):
    the package's design nominal (``builtin:seed004_nominal``, f 70 mm at (511.5, 511.5)) moved further from the
    truth."""
    return replace(load_params("builtin:seed004_nominal"), focal_length_mm=72.0, principal_point_px=(512.0, 512.0))


#: Stars are drawn at least this far inside the detector's pixel-centre extent [px], so that noise never takes a
#: centroid off the detector (0.05 px noise is 40 sigma away).
FRAME_MARGIN_PX = 2.0


@dataclass
class Frame:
    x_px: np.ndarray
    y_px: np.ndarray
    r: np.ndarray  # (N, 3) reference unit vectors
    identified: np.ndarray  # bool
    misidentified: np.ndarray  # bool: r is another star's direction


def make_frame(
    camera: CameraParams,
    rng: np.random.Generator,
    n_stars: int,
    noise_px: float,
    misid_fraction: float = 0.0,
) -> Frame:
    """One frame: n_stars uniformly on the detector (:data:`FRAME_MARGIN_PX` margin), their true directions rotated
    to a random attitude as references, centroids with N(0, noise_px) per axis. A misidentified star gets the
    reference of a random direction elsewhere in the field (a wrong catalogue star)."""
    w, h = camera.image_size_px
    theta = camera.model_vector()
    lo, hi_x, hi_y = FRAME_MARGIN_PX, w - 1.0 - FRAME_MARGIN_PX, h - 1.0 - FRAME_MARGIN_PX
    x_true = rng.uniform(lo, hi_x, n_stars)
    y_true = rng.uniform(lo, hi_y, n_stars)
    b = pixels_to_unit(x_true, y_true, theta)
    c = random_rotations(rng, 1)[0]
    r = b @ c  # b = C r  =>  r = C^T b
    mis = rng.random(n_stars) < misid_fraction
    if np.any(mis):
        xo = rng.uniform(lo, hi_x, int(mis.sum()))
        yo = rng.uniform(lo, hi_y, int(mis.sum()))
        r[mis] = pixels_to_unit(xo, yo, theta) @ c
    x = x_true + rng.normal(0.0, noise_px, n_stars)
    y = y_true + rng.normal(0.0, noise_px, n_stars)
    return Frame(x, y, r, np.ones(n_stars, bool), mis)


def make_frames(
    camera: CameraParams,
    n_frames: int,
    noise_px: float,
    min_stars: int = 10,
    max_stars: int = 30,
    misid_fraction: float = 0.0,
    seed: int = 0,
    focal_mm: np.ndarray | None = None,
) -> list[Frame]:
    """``n_frames`` frames of min..max stars; ``focal_mm`` (array per frame) overrides the focal length (drift)."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n_frames):
        cam = camera if focal_mm is None else camera.with_focal_length_mm(float(focal_mm[k]))
        n = int(rng.integers(min_stars, max_stars + 1))
        frames.append(make_frame(cam, rng, n, noise_px, misid_fraction))
    return frames


def sky_frames(seed: int, n_frames: int, noise_px: float = 0.05):
    """(true camera, frames as (x, y, r, identified), information (10, 10) at the truth) of a session of the
    real-sky simulator (seed 004's setup)."""
    from hostlink.sky.references import session_references
    from hostlink.sky.simulate import seed004_config, simulate

    result = simulate(seed004_config(n_frames, seed=seed))
    camera = params_from_dict(result.truth["camera"])
    s = result.session
    r_all = session_references(s).r
    ident = (s.star_id != 0) & np.all(np.isfinite(r_all), axis=1)
    bad = ~ident
    bad[np.array(result.truth["misidentified_rows"], dtype=int)] = True
    theta = camera.model_vector()
    frames = []
    info = np.zeros((theta.shape[0], theta.shape[0]))
    for rows in s.frame_slices():
        frames.append((s.x_px[rows], s.y_px[rows], r_all[rows], ident[rows]))
        keep = ~bad[rows]
        info += interstar_frame_information(s.x_px[rows][keep], s.y_px[rows][keep], theta, noise_px)
    return camera, frames, info


def synth_frames(seed: int, n_frames: int, noise_px: float = 0.05):
    """Like :func:`sky_frames` for :func:`make_frames` of seed 004's camera (10-30 stars uniformly on the
    detector)."""
    camera = seed004_true_camera()
    frames = make_frames(camera, n_frames, noise_px, seed=seed)
    info = interstar_information(camera, frames, noise_px)
    return camera, [(f.x_px, f.y_px, f.r, f.identified) for f in frames], info
