"""Passes over the data: per chunk of frames, the attitudes eliminated at a camera and the reduced normal equations,
the robust cost and the residual histogram summed (:class:`PassSums`, which chunks and workers merge in any
grouping); a final pass also gives the unit-weight matrix (the covariance), the stars beyond the gate, and the sums
without them (the regated pass that starts the next round).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks, measured_directions, take_frames
from hostlink.calibration.frames import apply_attitude_increment, inverse_3x3, triad_attitudes, wahba_attitudes
from hostlink.calibration.model import (
    CameraTerms,
    angle_arcsec,
    attitude_terms,
    camera_terms,
    observation_terms,
    residual_lengths,
    rotate,
    whitened_by_noise,
)
from hostlink.calibration.normal import NormalBlocks, attitude_normal, normal_blocks, reduced_normal, unit_weight_normal
from hostlink.calibration.robust import RAYLEIGH_MEDIAN, huber_rho, huber_weights
from hostlink.calibration.source import ChunkSource, frames_of, without_rows
from onboard.camera import offsets_to_unit

#: Gauss-Newton steps of each frame's attitude at a fixed camera, from the closed-form TRIAD start
#: (:func:`frame_attitudes`): the start is within ~2e-4 rad (centroid noise over the lever arm of one star) and one
#: step of this nearly linear 3-parameter problem squares the error (to ~1e-8 rad, 1e-3 of the attitude noise). The
#: camera step does not depend on what is left to first order (the Schur right-hand side carries g_phi), and the
#: cost only to second order (~1e-9 px^2 per frame).
ATTITUDE_STEPS = 1


#: Histogram of residual lengths for the robust scale: log-spaced bins over [1e-6, 1e3] px. Integer counts add up
#: exactly over chunks and workers, so the scale does not depend on how the frames are split; the median is
#: interpolated within a bin 0.25 % wide (the scale is used only for Huber weights and the 5-sigma gate).
SCALE_HIST_RANGE_PX = (1e-6, 1e3)


SCALE_HIST_BINS = 8192


def residual_histogram(norm_px: np.ndarray) -> np.ndarray:
    """Counts (SCALE_HIST_BINS,) of residual lengths [px] in the log-spaced bins of :data:`SCALE_HIST_RANGE_PX`
    (values outside go to the end bins)."""
    lo, hi = np.log(SCALE_HIST_RANGE_PX[0]), np.log(SCALE_HIST_RANGE_PX[1])
    pos = (np.log(np.maximum(norm_px, 1e-300)) - lo) * (SCALE_HIST_BINS / (hi - lo))
    idx = np.clip(pos.astype(np.int64), 0, SCALE_HIST_BINS - 1)
    return np.bincount(idx, minlength=SCALE_HIST_BINS).astype(np.int64)


def robust_sigma_from_histogram(hist: np.ndarray) -> float:
    """Per-axis sigma [px] from a :func:`residual_histogram`: its median (log-interpolated within the bin) over
    sqrt(2 ln 2), as :func:`hostlink.calibration.robust.robust_sigma_2d` does with the exact median."""
    n = int(hist.sum())
    if n == 0:
        return float("nan")
    cum = np.cumsum(hist)
    half = 0.5 * n
    k = int(np.searchsorted(cum, half, side="left"))
    below = cum[k] - hist[k]
    frac = (half - below) / max(hist[k], 1)
    lo, hi = np.log(SCALE_HIST_RANGE_PX[0]), np.log(SCALE_HIST_RANGE_PX[1])
    width = (hi - lo) / SCALE_HIST_BINS
    return float(np.exp(lo + (k + frac) * width) / RAYLEIGH_MEDIAN)


def robust_weights(norm: np.ndarray, sigma_px: float, huber_k: float) -> np.ndarray:
    return np.ones_like(norm) if not np.isfinite(sigma_px) else huber_weights(norm, sigma_px, huber_k)


def frame_attitudes(
    data: CalibrationData,
    theta: np.ndarray,
    sigma_px: float = np.inf,
    huber_k: float = 3.0,
    cam: CameraTerms | None = None,
) -> np.ndarray:
    """The attitude of every frame (M, 3, 3) that minimises its robust whitened cost at the camera ``theta``:
    TRIAD from the measured directions (:func:`hostlink.calibration.frames.triad_attitudes`), then
    :data:`ATTITUDE_STEPS` Gauss-Newton steps with the Huber weights of scale ``sigma_px`` (inf: plain least
    squares), each star whitened by its own noise when ``data`` gives it
    (:func:`hostlink.calibration.model.whitened_by_noise`; ``sigma_px`` is then a scale of those). A function of
    each frame alone, so the same for any split of the frames into chunks. With the attitudes eliminated this way
    the camera is fitted on the reduced cost sum_f min_C_f rho(e_f) (variable projection, Golub and Pereyra 1973),
    whose Gauss-Newton matrix is the Schur complement of :func:`hostlink.calibration.normal.reduced_normal`.
    ``cam``: the stars' :func:`camera_terms` at ``theta`` when already computed (the directions are then (q, F)
    normalised, the same numbers as ``measured_directions``)."""
    b = measured_directions(data, theta) if cam is None else offsets_to_unit(cam.q[:, 0], cam.q[:, 1], theta[0])
    att = triad_attitudes(b, data.r, data.frame_starts)
    for _ in range(ATTITUDE_STEPS):
        att_obs = np.repeat(att, data.counts, axis=0)
        e, jp = attitude_terms(data.x_px, data.y_px, data.r, att_obs, theta, cam)
        if data.sigma_px is not None:
            e, jp = whitened_by_noise(data.sigma_px, e, jp)
        w = robust_weights(residual_lengths(e), sigma_px, huber_k)
        a, g = attitude_normal(e, jp, w, data.frame_starts)
        step = np.einsum("mij,mj->mi", inverse_3x3(a), g)
        att = apply_attitude_increment(att, -step)
    return att


def initial_attitudes(data: CalibrationData, theta: np.ndarray) -> np.ndarray:
    """Per-frame least-squares attitude from the measured directions of the given camera (Markley's rotation,
    :func:`hostlink.calibration.frames.wahba_attitudes`)."""
    return wahba_attitudes(measured_directions(data, theta), data.r, data.frame_starts)


@dataclass
class PassSums:
    """What one pass over the frames adds up; every field is a sum (or a max, or a union) over frames, so chunks
    and workers merge in any grouping (:meth:`merge`) to the same numbers up to the order of floating additions."""

    s: np.ndarray  # (K, K) reduced normal matrix (Schur complement), scaled camera columns
    rhs: np.ndarray  # (K,) its right-hand side
    cost: float  # robust cost at the pass's camera
    sum_e2: float  # sum |e|^2 [px^2]
    n_obs: int
    n_frames: int
    hist: np.ndarray  # residual_histogram of |e|
    over_gate: np.ndarray  # source rows whose |e| exceeds the gate given to the pass (int64)
    max_e_px: float = 0.0
    s_unit: np.ndarray | None = None  # final pass: S with unit weights, unscaled columns (the covariance)
    u_diag_unit: np.ndarray | None = None  # final pass: diag of U with unit weights, unscaled (degeneracies)
    #: final pass: the (non-final) sums of the same pass without the stars in ``over_gate`` (and the frames they
    #: leave with fewer than three stars), i.e. the pass that starts the next round after gating, without a pass
    regated: PassSums | None = None
    #: final pass: sum and maximum of the squared / largest angle [arcsec] between each star's measured direction
    #: and its attitude-rotated reference (the report's residuals in arcsec, ``report.residual_sums``)
    sum_arcsec2: float = 0.0
    max_arcsec: float = 0.0
    #: sum of the squared residuals the fit weighs: |e|^2 [px^2], or |e / sigma_k|^2 of stars of given noise
    sum_z2: float = 0.0

    def merge(self, other: PassSums) -> PassSums:
        def add(a, b):
            return None if a is None or b is None else a + b

        regated = None if self.regated is None or other.regated is None else self.regated.merge(other.regated)

        return PassSums(
            self.s + other.s,
            self.rhs + other.rhs,
            self.cost + other.cost,
            self.sum_e2 + other.sum_e2,
            self.n_obs + other.n_obs,
            self.n_frames + other.n_frames,
            self.hist + other.hist,
            np.concatenate([self.over_gate, other.over_gate]),
            max(self.max_e_px, other.max_e_px),
            add(self.s_unit, other.s_unit),
            add(self.u_diag_unit, other.u_diag_unit),
            regated,
            self.sum_arcsec2 + other.sum_arcsec2,
            max(self.max_arcsec, other.max_arcsec),
            self.sum_z2 + other.sum_z2,
        )


def empty_pass(k: int, final: bool = False, regated: bool = True) -> PassSums:
    """Zero sums of K camera columns; ``final``: with the unit-weight sums and (``regated``) the sums without the
    gated stars, themselves final ones (:func:`chunk_pass`)."""
    z = np.zeros(0, dtype=np.int64)
    after = empty_pass(k, True, False) if regated else None
    unit = (np.zeros((k, k)), np.zeros(k), after) if final else (None, None, None)
    return PassSums(np.zeros((k, k)), np.zeros(k), 0.0, 0.0, 0, 0, np.zeros(SCALE_HIST_BINS, np.int64), z, 0.0, *unit)


@dataclass(frozen=True)
class PassRequest:
    """One pass over the frames: the camera, the scale of the Huber weights (inf: none), the columns and their
    scales, and what to leave out. ``final``: also the normal matrix with unit weights and unscaled columns (the
    covariance), and the stars beyond ``gate_px`` listed."""

    theta: np.ndarray
    sigma_px: float
    cols: np.ndarray
    col_scale: np.ndarray
    excluded_rows: np.ndarray
    huber_k: float
    chunk_obs: int
    final: bool = False
    gate_px: float = np.inf


def chunk_pass(data: CalibrationData, req: PassRequest) -> PassSums:
    """The sums of one chunk of frames (whole frames) for ``req``: per sub-chunk of at most ``chunk_obs`` stars,
    attitudes eliminated (:func:`frame_attitudes`), residuals and Jacobians (:func:`observation_terms`), Huber
    weights, normal blocks (:func:`normal_blocks`) reduced at once by the Schur complement
    (:func:`reduced_normal`), robust cost and residual histogram."""
    out = empty_pass(req.cols.size, req.final)
    for f0, f1 in frame_chunks(data.frame_starts, req.chunk_obs):
        sub = without_rows(frames_of(data, f0, f1), req.excluded_rows)
        if sub.n_frames == 0:
            continue
        frame_sums: list = []
        part = _checked_sums(sub, req, frame_sums)
        if part is None:
            out.cost = np.inf  # a camera some frame cannot be fitted with: the step is rejected
            return out
        if req.final:
            # the next round's first pass, after gating, for this sub-chunk: the same sums when no star of it is
            # beyond the gate, else those sums with the frames of the gated stars summed again without them (what
            # that pass computes, to the rounding of the sums). It is a final pass too (unit-weight sums, stars
            # beyond the same gate): when the next round's first step is already below the tolerance, it ends that
            # round without a pass of its own
            part.regated = replace(part) if part.over_gate.size == 0 else _regated(sub, part, frame_sums[0], req)
        out = out.merge(part)
    return out


def _regated(sub: CalibrationData, part: PassSums, frame_sums: np.ndarray, req: PassRequest) -> PassSums:
    """The final sums ``part`` of the sub-chunk ``sub`` without its stars beyond the gate (``part.over_gate``), their
    frames' attitudes fitted anew and the frames left with fewer than three stars dropped, as a pass without them
    gives them: only the frames holding those stars are summed again (with and without them). The matrices take out
    the first and add the second sums; the residuals' sums and maxima add the other frames' own (``frame_sums``, of
    :func:`_sub_chunk_sums`: no difference of large sums when a gated star's residual is huge) to the new ones.
    A frame that cannot be summed again makes the cost infinite (the step is rejected), as in a pass."""
    k = req.cols.size
    gated = np.sort(part.over_gate)
    rows = sub.source_rows()
    hit = gated[np.minimum(np.searchsorted(gated, rows), gated.size - 1)] == rows
    affected = np.unique(sub.frame_index()[hit])
    frames = take_frames(sub, affected)
    # every frame holds a gated star (as often): the frames summed again are the sub-chunk's, their sums ``part``
    before = part if affected.size == sub.n_frames else _checked_sums(frames, req)
    left = without_rows(frames, gated)
    after = _checked_sums(left, req) if left.n_frames else empty_pass(k, True, False)
    if before is None or after is None:
        failed = empty_pass(k, True, False)
        failed.cost = np.inf
        return failed
    others = np.ones(sub.n_frames, dtype=bool)
    others[affected] = False
    max_e, max_arcsec, sum_e2, sum_arcsec2, cost, sum_z2 = frame_sums[:, others]
    return PassSums(
        part.s - before.s + after.s,
        part.rhs - before.rhs + after.rhs,
        float(np.sum(cost)) + after.cost,
        float(np.sum(sum_e2)) + after.sum_e2,
        part.n_obs - before.n_obs + after.n_obs,
        part.n_frames - before.n_frames + after.n_frames,
        part.hist - before.hist + after.hist,
        after.over_gate,
        max(float(max_e.max(initial=0.0)), after.max_e_px),
        part.s_unit - before.s_unit + after.s_unit,
        part.u_diag_unit - before.u_diag_unit + after.u_diag_unit,
        None,
        float(np.sum(sum_arcsec2)) + after.sum_arcsec2,
        max(float(max_arcsec.max(initial=0.0)), after.max_arcsec),
        float(np.sum(sum_z2)) + after.sum_z2,
    )


def _checked_sums(sub: CalibrationData, req: PassRequest, frame_sums: list | None = None) -> PassSums | None:
    """:func:`_sub_chunk_sums`, or None when some frame's terms are not finite at the request's camera."""
    try:
        with np.errstate(all="ignore"):  # a trial camera far off can make a frame's terms non-finite
            part = _sub_chunk_sums(sub, req, frame_sums)
    except np.linalg.LinAlgError:
        return None
    return part if np.isfinite(part.cost) and np.all(np.isfinite(part.s)) else None


def _sub_chunk_sums(sub: CalibrationData, req: PassRequest, frame_sums: list | None = None) -> PassSums:
    """The sums of :func:`chunk_pass` for the sub-chunk ``sub``. A final request appends to ``frame_sums`` (when
    given) each frame's largest |e| and arcsec angle, and its sums of |e|^2, of the squared angles, of the robust
    cost and of the weighed squares (``sum_z2``), (6, M) (:func:`_regated`)."""
    cam = camera_terms(sub.x_px, sub.y_px, req.theta)
    att = frame_attitudes(sub, req.theta, req.sigma_px, req.huber_k, cam)
    att_obs = np.repeat(att, sub.counts, axis=0)
    e, jt, jp = observation_terms(sub.x_px, sub.y_px, sub.r, att_obs, req.theta, req.cols, cam)
    norm_px = residual_lengths(e)  # in pixels, for the residual statistics
    if sub.sigma_px is not None:
        e, jt, jp = whitened_by_noise(sub.sigma_px, e, jt, jp)
    norm = residual_lengths(e) if sub.sigma_px is not None else norm_px  # what the fit weighs and gates
    w = robust_weights(norm, req.sigma_px, req.huber_k)
    rho = huber_rho(norm, req.sigma_px, req.huber_k)
    blocks = NormalBlocks(*normal_blocks(e, jt, jp, w, sub.frame_starts, req.col_scale), e)
    s, rhs, _ = reduced_normal(blocks, 0.0)
    unit, arcsec = (None, None), (0.0, 0.0)
    if req.final:
        s_unit, u_diag_unit = unit_weight_normal(blocks, s, jt, jp, w, sub.frame_starts, req.col_scale)
        unit = (s_unit / np.outer(req.col_scale, req.col_scale), u_diag_unit / req.col_scale**2)  # unscaled columns
        b = offsets_to_unit(cam.q[:, 0], cam.q[:, 1], req.theta[0])
        ang = angle_arcsec(b, rotate(att_obs, sub.r))
        arcsec = (float(np.sum(ang * ang)), float(ang.max(initial=0.0)))
        if frame_sums is not None:
            starts = sub.frame_starts[:-1]
            per_frame = [np.maximum.reduceat(norm_px, starts), np.maximum.reduceat(ang, starts)]
            per_frame += [np.add.reduceat(x, starts) for x in (norm_px * norm_px, ang * ang, rho, norm * norm)]
            frame_sums.append(np.stack(per_frame))
    return PassSums(
        s,
        rhs,
        float(np.sum(rho)),
        float(np.sum(norm_px * norm_px)),
        sub.n_obs,
        sub.n_frames,
        residual_histogram(norm),
        sub.source_rows()[norm > req.gate_px].astype(np.int64),
        float(norm_px.max(initial=0.0)),
        *unit,
        None,
        *arcsec,
        sum_z2=float(np.sum(norm * norm)),
    )


def serial_pass(source: ChunkSource, req: PassRequest) -> PassSums:
    """Run :func:`chunk_pass` over every chunk in this process, one chunk in memory at a time, in order."""
    out = empty_pass(req.cols.size, req.final)
    for chunk in source:
        out = out.merge(chunk_pass(chunk, req))
    return out


#: A pass runner: (source, request) -> sums over all chunks. :func:`serial_pass`, or a Dask one.
PassRunner = Callable[[ChunkSource, PassRequest], PassSums]
