"""Robustness against misidentified stars, false matches and a poor nominal: a pre-pass, interstar voting, Huber
weights, residual gating.

0. Pre-pass (:func:`estimate_scale_and_parity`): the focal length from the identified stars' own interstar angles
   (a nominal off by a factor of 0.1 to 10 was tested, e.g. the pixel pitch of an unbinned detector: it starts where
   a good one would),
   and the parity (a mirrored image keeps every interstar angle but reverses the handedness of every star triple).
1. Voting (before any fit): interstar angles are invariant under the unknown attitude (seed 000 eq. 3), so a star
   whose angles to most other stars of its frame disagree with the catalogue's is misidentified. The tolerance is
   generous enough for an uncalibrated nominal camera (a relative focal-length error plus a few pixels).
2. Huber loss during the fit (IRLS weights), so what voting missed cannot pull the solution far.
3. Gating after convergence: residuals beyond ``gate`` robust sigmas are dropped and the fit is repeated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import (
    CalibrationData,
    frame_chunks,
    padded_frames,
    pair_angles_upper_rad,
    upper_pairs,
)
from onboard.camera import pixels_to_unit

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
        pairs = upper_pairs(nmax)
        pair_ok = valid[:, pairs[0]] & valid[:, pairs[1]]
        ang_b = pair_angles_upper_rad(pf.b, pairs, pair_ok)
        ang_r = pair_angles_upper_rad(pf.r, pairs, pair_ok)
        agree = (np.abs(ang_b - ang_r) <= rel_tol * ang_r + abs_tol_rad) & pair_ok
        # each star's agreeing pairs: pair p counts for both its stars (0/1 sums, exact in floating point)
        incidence = np.zeros((pairs[0].size, nmax))
        incidence[np.arange(pairs[0].size), pairs[0]] = 1.0
        incidence[np.arange(pairs[0].size), pairs[1]] = 1.0
        others = np.maximum(valid.sum(axis=1) - 1, 1)
        frac = (agree.astype(np.float64) @ incidence) / others[:, None]
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


#: Pre-pass: width of the densest-window (mode) search on log(angle ratio). The search is not bounded (a factor of
#: 0.1 to 10 was tested); the window holds the pairs of a field whose distortion changes the local scale by ~1 %, and
#: the iteration through the rescaled camera narrows what is left.
SCALE_MODE_WINDOW = 0.02
#: Pre-pass: pairs shorter than this fraction of a frame's longest pair carry their centroid errors as a large
#: relative angle error; they do not vote on the scale.
SCALE_MIN_PAIR_FRACTION = 0.2
#: Pre-pass: triples whose spanned volume |det[r1 r2 r3]| is below this fraction of the largest of their frame are
#: too close to collinear for the sign of the determinant to be trusted.
PARITY_MIN_VOLUME_FRACTION = 0.05
#: Pre-pass: most random triples per frame examined for the parity.
PARITY_TRIPLES_PER_FRAME = 40
#: Pre-pass: most frames it looks at (evenly spaced through the session): ~10^5 pairs and triples settle the scale
#: to ~1e-5 and the parity beyond doubt, and the pre-pass costs the same for 10^3 or 10^6 frames.
PREPASS_MAX_FRAMES = 1000


@dataclass(frozen=True)
class ScaleParity:
    """What the identified stars say about the nominal camera before any fit (:func:`estimate_scale_and_parity`).

    scale: F_true / F_nominal, the focal-length ratio (1.0 when no pair could vote).
    n_pairs: star pairs that voted on the scale (inside the densest window).
    mirrored_fraction: of the triples of consistent stars, the fraction whose handedness in the camera frame is
    opposite to the sky's (0 for a correct detector, 1 for a mirrored one); NaN when no triple qualified.
    n_triples: triples that voted on the parity.
    """

    scale: float
    n_pairs: int
    mirrored_fraction: float
    n_triples: int

    @property
    def mirrored(self) -> bool:
        return bool(self.n_triples > 0 and self.mirrored_fraction > 0.5)


def _densest_window(values: np.ndarray, width: float) -> tuple[float, int]:
    """Median of the values inside the window of the given width that holds the most of them (a mode estimate:
    unlike the median it survives more than 50 % of outliers when they are spread out), and that count."""
    v = np.sort(values)
    upper = np.searchsorted(v, v + width, side="right")
    counts = upper - np.arange(v.size)
    i = int(np.argmax(counts))
    return float(np.median(v[i : upper[i]])), int(counts[i])


def _pair_log_ratios(data: CalibrationData, b: np.ndarray, chunk_obs: int) -> np.ndarray:
    """log(angle_b / angle_r) over every pair of every frame whose catalogue angle is at least
    :data:`SCALE_MIN_PAIR_FRACTION` of its frame's longest (small angles: angle_b / angle_r = F_true / F_nominal)."""
    out = []
    for f0, f1 in frame_chunks(data.frame_starts, chunk_obs):
        pf = padded_frames(data, b, f0, f1)
        nmax = pf.valid.shape[1]
        if nmax < 2:
            continue
        pairs = upper_pairs(nmax)
        upper = pf.valid[:, pairs[0]] & pf.valid[:, pairs[1]]
        ang_b = pair_angles_upper_rad(pf.b, pairs, upper)
        ang_r = pair_angles_upper_rad(pf.r, pairs, upper)
        longest = np.max(np.where(upper, ang_r, 0.0), axis=1)
        use = upper & (ang_r >= SCALE_MIN_PAIR_FRACTION * longest[:, None]) & (ang_r > 0) & (ang_b > 0)
        out.append(np.log(ang_b[use] / ang_r[use]))
    return np.concatenate(out) if out else np.zeros(0)


def estimate_scale(data: CalibrationData, theta: np.ndarray, chunk_obs: int = 20_000) -> tuple[float, int]:
    """F_true / F_nominal from the identified stars themselves: the interstar angles measured through the camera
    ``theta`` (model vector, F in px) against the catalogue's. For a pinhole, tan(angle) scales as 1 / F for pairs
    through the boresight, so the ratio angle_b / angle_r of every long pair votes for F_true / F_nominal; the
    densest 2 % window of log ratios (:data:`SCALE_MODE_WINDOW`) wins, so misidentified stars do not pull it. The
    estimate is iterated three times (each through the rescaled camera) to remove the wide-field nonlinearity.
    Returns (scale, number of pairs in the winning window); (1.0, 0) when no pair votes."""
    theta = np.array(theta, dtype=np.float64)
    scale, n = 1.0, 0
    for _ in range(3):
        ratios = _pair_log_ratios(data, pixels_to_unit(data.x_px, data.y_px, theta), chunk_obs)
        if ratios.size == 0:
            return 1.0, 0
        log_step, n = _densest_window(ratios, SCALE_MODE_WINDOW)
        step = math.exp(log_step)
        scale *= step
        theta[0] *= step
        if abs(log_step) < 1e-5:  # 0.001 %: far inside the voting tolerance, and the fit refines it anyway
            break
    return scale, n


def triple_handedness(
    data: CalibrationData, b: np.ndarray, consistent: np.ndarray, seed: int = 0, chunk_obs: int = 20_000
) -> tuple[int, int]:
    """(triples with opposite handedness, triples examined): for up to :data:`PARITY_TRIPLES_PER_FRAME` random
    triples of ``consistent`` stars per frame, sign(det[b1 b2 b3]) against sign(det[r1 r2 r3]). A rotation keeps
    the sign of every triple product; a mirror (one flipped image axis) reverses it, while it keeps every interstar
    angle, so only this test finds it. Triples too close to collinear (:data:`PARITY_MIN_VOLUME_FRACTION`) are
    skipped. Deterministic for a given ``seed``."""
    rng = np.random.default_rng(seed)
    opposite = total = 0
    for f0, f1 in frame_chunks(data.frame_starts, chunk_obs):
        pf = padded_frames(data, b, f0, f1)
        valid = pf.valid.copy()
        valid[pf.frame, pf.slot] &= consistent[pf.rows]
        nmax = valid.shape[1]
        if nmax < 3:
            continue
        m = valid.shape[0]
        k = PARITY_TRIPLES_PER_FRAME
        # random slots among the valid ones: rank random keys, invalid slots last
        keys = rng.random((m, k, nmax)) + np.where(valid, 0.0, 2.0)[:, None, :]
        idx = np.argsort(keys, axis=2)[:, :, :3]
        ok = np.take_along_axis(np.broadcast_to(valid[:, None, :], keys.shape), idx, axis=2).all(axis=2)
        fr = np.arange(m)[:, None, None]
        det_b = np.linalg.det(pf.b[fr, idx])
        det_r = np.linalg.det(pf.r[fr, idx])
        biggest = np.max(np.where(ok, np.abs(det_r), 0.0), axis=1, keepdims=True)
        ok &= np.abs(det_r) >= PARITY_MIN_VOLUME_FRACTION * biggest
        ok &= det_r != 0
        opposite += int(np.count_nonzero(ok & (np.sign(det_b) != np.sign(det_r))))
        total += int(np.count_nonzero(ok))
    return opposite, total


def estimate_scale_and_parity(data: CalibrationData, theta: np.ndarray, chunk_obs: int = 20_000) -> ScaleParity:
    """The pre-pass before voting (:func:`estimate_scale`, then :func:`triple_handedness` over the stars that
    the interstar vote at the rescaled focal length finds consistent), on at most :data:`PREPASS_MAX_FRAMES`
    evenly spaced frames (:func:`prepass_frames`; the chunked path gathers the same frames from its chunks and
    calls :func:`scale_and_parity_of_sample`)."""
    if data.n_frames > PREPASS_MAX_FRAMES:
        frames = np.zeros(data.n_frames, dtype=bool)
        frames[prepass_frames(data.n_frames)] = True
        data = data.select(frames[data.frame_index()], min_stars=1)[0]
    return scale_and_parity_of_sample(data, theta, chunk_obs)


def prepass_frames(n_frames: int) -> np.ndarray:
    """Indices (sorted, unique) of the at most :data:`PREPASS_MAX_FRAMES` evenly spaced frames the pre-pass uses."""
    if n_frames <= PREPASS_MAX_FRAMES:
        return np.arange(n_frames, dtype=np.int64)
    return np.unique(np.linspace(0, n_frames - 1, PREPASS_MAX_FRAMES).round().astype(np.int64))


def scale_and_parity_of_sample(data: CalibrationData, theta: np.ndarray, chunk_obs: int = 20_000) -> ScaleParity:
    """The pre-pass of :func:`estimate_scale_and_parity` on frames already sampled."""
    scale, n_pairs = estimate_scale(data, theta, chunk_obs)
    theta_s = np.array(theta, dtype=np.float64)
    theta_s[0] *= scale
    b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    consistent = vote_consistent_stars(data, b, chunk_obs=chunk_obs)
    opposite, total = triple_handedness(data, b, consistent, chunk_obs=chunk_obs)
    return ScaleParity(scale, n_pairs, opposite / total if total else float("nan"), total)
