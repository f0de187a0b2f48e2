"""One calibration run: pick the method, reject outliers, fit, and gather everything the result file reports."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.calibration.bundle import BundleOptions, bundle_adjust_chunks
from hostlink.calibration.data import (
    MIN_STARS_PER_FRAME,
    SPOOL_SUFFIX,
    CalibrationData,
    calibration_data_from_session,
    chunk_frame_count,
    concatenate_data,
    frame_chunks,
    load_chunk,
    measured_directions,
    save_chunk,
    session_chunk_data,
    take_frames,
)
from hostlink.calibration.interstar_methods import calibrate_interstar
from hostlink.calibration.model import ARCSEC_PER_RAD, DEFAULT_CHUNK_OBS, residuals
from hostlink.calibration.normal import covariance_from_normal
from hostlink.calibration.passes import PassRunner, frame_attitudes, serial_pass
from hostlink.calibration.report import (
    RejectedStars,
    clipped_rms,
    degeneracies,
    fitted_attitudes,
    interstar_rms_rad,
    interstar_sums_of_directions,
    merge_sums,
    rejected_stars,
    residual_stats,
    residual_sums,
    sigma_dict,
    stats_from_sums,
    undetermined_parameters,
)
from hostlink.calibration.robust import (
    ScaleParity,
    consistent_stars_and_field,
    estimate_scale_and_parity,
    max_pair_angle_rad,
    prepass_frames,
    robust_sigma_2d,
    scale_and_parity_of_sample,
    vote_consistent_stars,
)
from hostlink.calibration.seed004 import SEED004_ESTIMATE, calibrate_seed004
from hostlink.calibration.source import ChunkSource, frames_of, in_memory_source, without_rows
from hostlink.errors import UserError
from hostlink.files.session import Session, check_on_detector
from hostlink.sky.references import ABERRATION_MAX_RAD, SessionReferences
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams, ParameterError, validate_params
from onboard.site import Site, Weather

METHODS = ("bundle", "cosine", "sine", "improved-cosine", "improved-sine", "seed004")
#: seed 000's methods: (observation equation, two-step improved iteration of sec. 2)
INTERSTAR_METHODS = {
    "cosine": ("cos", False),
    "sine": ("sin", False),
    "improved-cosine": ("cos", True),
    "improved-sine": ("sin", True),
}
#: Gate for the interstar methods' post-fit outlier check, in robust sigmas (as the bundle's).
GATE_SIGMAS = 5.0
#: A calibration that rejects more than this fraction of the identified stars it was given (interstar voting,
#: residual gating, and the stars of frames left with fewer than three) has failed: most of its input disagrees
#: with the camera it found, so the camera describes a minority (a wrong nominal or wrong identifications).
MAX_REJECTED_FRACTION = 0.5


@dataclass
class CalibrationOutcome:
    method: str
    params: CameraParams
    theta: np.ndarray
    estimate: tuple[str, ...]
    covariance: np.ndarray
    sigma_px: float
    sigma_estimated_px: float
    data: CalibrationData  # rows used in the final fit
    attitudes: np.ndarray  # per frame of ``data``
    before: dict
    after: dict
    interstar_before_rad: float
    interstar_after_rad: float
    rejected: dict
    degeneracies: dict
    history: list[dict] = field(default_factory=list)
    converged: bool = True
    stages: list[dict] = field(default_factory=list)
    #: the pre-pass before voting (:func:`hostlink.calibration.robust.estimate_scale_and_parity`), as reported
    prepass: dict = field(default_factory=dict)
    #: parameters held at nominal because the data cannot determine them (:func:`report.undetermined_parameters`)
    held: list[dict] = field(default_factory=list)
    #: the rows of the input data: rejected by interstar voting, and by residual gating (bool, input rows)
    voted_out: np.ndarray | None = None
    gated: np.ndarray | None = None
    #: set by :func:`calibrate_session`: every identified star of the session not used, and the note on the loss
    #: of a session without time (None when the time is known)
    rejected_stars: RejectedStars | None = None
    time_note: str | None = None
    #: stars and frames of the final fit (the chunked path has no ``data`` in memory: ``data`` is None there)
    n_stars_used: int = 0
    n_frames_used: int = 0
    #: the largest catalogue angle between two stars of one frame [rad] (for :func:`time_unknown_note`)
    field_rad: float = float("nan")

    def sigma(self) -> dict:
        return sigma_dict(self.estimate, self.covariance, self.params)

    def failure(self) -> str | None:
        """Why this result must not be used as a calibration (one line), or None: the fit did not converge, or
        more than :data:`MAX_REJECTED_FRACTION` of the identified stars were rejected."""
        if not self.converged:
            return (
                f"the fit did not converge in {len(self.history)} iterations (raise --max-iter, or check the "
                "nominal and the identifications)"
            )
        rej = self.rejected
        n_in = self.n_stars_used + rej["total_stars"]
        if n_in and rej["total_stars"] > MAX_REJECTED_FRACTION * n_in:
            return (
                f"{rej['total_stars']} of {n_in} identified stars ({100 * rej['total_stars'] / n_in:.0f} %, more "
                f"than {100 * MAX_REJECTED_FRACTION:.0f} %) were rejected ({rej['voting']} by interstar voting, "
                f"{rej['gating']} by residual gating, the rest with their frames): the identifications or the "
                "nominal are wrong"
            )
        return None


def mirrored_message(prepass: ScaleParity, image_size_px: tuple[int, int]) -> str:
    """The one-line explanation of a mirrored detector (odd parity) and how to fix it."""
    return (
        f"the image is mirrored: odd parity (in {100 * prepass.mirrored_fraction:.0f} % of {prepass.n_triples} "
        "star triples the handedness in the camera frame is opposite to the sky's, which no rotation can do); flip "
        f"x (x_px -> {image_size_px[0] - 1} - x_px) in the session or in the sensor's readout, then calibrate again"
    )


def prepass_start(data: CalibrationData, nominal: CameraParams, scale_focal: bool) -> tuple[CameraParams, ScaleParity]:
    """The camera the fit starts from: the nominal with its focal length scaled by what the identified stars say
    (when ``scale_focal``), after checking the parity. Raises ValueError for a mirrored image."""
    prepass = estimate_scale_and_parity(data, nominal.model_vector(np.float64))
    return start_from_prepass(prepass, nominal, scale_focal), prepass


def start_from_prepass(prepass: ScaleParity, nominal: CameraParams, scale_focal: bool) -> CameraParams:
    """The camera the fit starts from, given the pre-pass (:func:`prepass_start`). Raises ValueError for a
    mirrored image."""
    if prepass.mirrored:
        raise ValueError(mirrored_message(prepass, nominal.image_size_px))
    if not scale_focal or prepass.n_pairs == 0:
        return nominal
    return nominal.with_focal_length_mm(nominal.focal_length_mm * prepass.scale)


def prepass_report(prepass: ScaleParity, nominal: CameraParams, start: CameraParams) -> dict:
    """The pre-pass as the result file reports it."""
    return {
        "focal_scale": prepass.scale,
        "scale_pairs": prepass.n_pairs,
        "nominal_focal_length_mm": nominal.focal_length_mm,
        "start_focal_length_mm": start.focal_length_mm,
        "mirrored_fraction": prepass.mirrored_fraction,
        "parity_triples": prepass.n_triples,
    }


def _interstar_with_gating(data, start, method, estimate, progress, consistent):
    fit_data, _, _ = data.select(consistent)
    if fit_data.n_frames == 0:
        raise ValueError("no frame with at least 3 consistent identified stars")
    gated = np.zeros(data.n_obs, dtype=bool)
    index = np.searchsorted(data.source_rows(), fit_data.source_rows())  # input row of each fit row (increasing)

    def fit(d):
        if method == "seed004":
            return calibrate_seed004(d, start, estimate or SEED004_ESTIMATE, progress=progress)
        form, improved = INTERSTAR_METHODS[method]
        return calibrate_interstar(d, start, form, improved, estimate or ESTIMATE_NAMES, progress=progress)

    result = fit(fit_data)
    for _ in range(2):  # gate once, refit, and confirm
        att = fitted_attitudes(fit_data, result.theta)
        norm = np.linalg.norm(residuals(fit_data, result.theta, att), axis=1)
        bad = norm > GATE_SIGMAS * robust_sigma_2d(norm)
        if not np.any(bad):
            break
        gated[index[bad]] = True
        fit_data, kept, _ = fit_data.select(~bad)
        index = index[kept]
        result = fit(fit_data)
    return result, fit_data, gated


def calibrate(
    data: CalibrationData,
    nominal: CameraParams,
    method: str = "bundle",
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    progress: Callable[[dict], None] | None = None,
) -> CalibrationOutcome:
    """Calibrate with one of :data:`METHODS`. Raises ValueError on a problem the data cannot support (among them
    a mirrored image, :func:`mirrored_message`).

    1. Pre-pass (:func:`prepass_start`): the focal length from the identified stars' interstar angles (when f is
       estimated) and the parity, so a nominal focal length far off (0.1 to 10 tested) starts where a good one would.
    2. Interstar voting (``robust.vote_consistent_stars``) at that camera.
    3. The fit. ``estimate`` None means the method's own set: for ``bundle`` every parameter the data determine
       (all ten, less those :func:`hostlink.calibration.report.undetermined_parameters` holds at nominal, which
       ``held`` lists with the reason); all ten for the improved methods, (f, x0, y0) for ``cosine``/``sine``
       (their papers' scope), (f, x0, y0, k1, k2) for ``seed004``. An explicit ``estimate`` is used as given."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    if method == "bundle":
        return calibrate_chunks(in_memory_source(data), nominal, estimate, noise_px, max_iter, progress, keep_data=data)
    theta0 = nominal.model_vector(np.float64)
    start, prepass = prepass_start(data, nominal, estimate is None or "f" in estimate)
    consistent = vote_consistent_stars(data, pixels_to_unit(data.x_px, data.y_px, start.model_vector(np.float64)))
    voted_out = ~consistent
    if start is nominal and prepass.n_pairs and abs(prepass.scale - 1.0) > 0.03 and not np.any(consistent):
        raise ValueError(
            f"no star agrees with the catalogue at the nominal focal length, which the stars say is "
            f"{100 * (1 / prepass.scale - 1):+.1f} % off: estimate f"
        )
    fit, fit_data, gated = _interstar_with_gating(data, start, method, estimate, progress, consistent)
    theta, normal, est, sigma_est = fit.theta, fit.normal, fit.estimate, fit.sigma_estimated_px
    att = fitted_attitudes(fit_data, theta)
    u_diag = None
    history, converged, stages = fit.history, fit.converged, fit.stages
    rejected = {
        "voting": int(np.sum(voted_out)),
        "gating": int(np.sum(gated)),
        "frames_dropped": int(data.n_frames - fit_data.n_frames),
        "total_stars": int(data.n_obs - fit_data.n_obs),
    }
    sigma = float(noise_px) if noise_px else sigma_est
    cov = covariance_from_normal(normal, sigma)
    params = nominal.with_model_vector(theta)
    att_before = fitted_attitudes(fit_data, theta0)
    return CalibrationOutcome(
        method=method,
        params=params,
        theta=theta,
        estimate=est,
        covariance=cov,
        sigma_px=sigma,
        sigma_estimated_px=sigma_est,
        data=fit_data,
        attitudes=att,
        before=residual_stats(fit_data, theta0, att_before),
        after=residual_stats(fit_data, theta, att),
        interstar_before_rad=interstar_rms_rad(fit_data, theta0),
        interstar_after_rad=interstar_rms_rad(fit_data, theta),
        rejected=rejected,
        degeneracies=degeneracies(normal, est, u_diag),
        history=history,
        converged=converged,
        stages=stages,
        prepass=prepass_report(prepass, nominal, start),
        voted_out=voted_out,
        gated=gated,
        n_stars_used=fit_data.n_obs,
        n_frames_used=fit_data.n_frames,
        field_rad=max_pair_angle_rad(fit_data),
    )


def _bundle_chunks(source, start, estimate, noise_px, max_iter, progress, excluded, run_pass, warm):
    options = BundleOptions(estimate=estimate, noise_px=noise_px, max_iter=max_iter, progress=progress)
    return bundle_adjust_chunks(source, start, options, excluded, run_pass, warm)


@dataclass
class _Screened:
    """What the voting pass over the chunks found: rejected source rows and the input's size."""

    voted_rows: np.ndarray
    n_stars: int
    n_frames: int
    field_rad: float


def _vote_chunk(data: CalibrationData, theta: np.ndarray) -> _Screened:
    """The voting pass over one chunk at the camera ``theta`` (and the field it spans, from the same Gram matrices:
    :func:`hostlink.calibration.robust.consistent_stars_and_field`)."""
    consistent, field_rad = consistent_stars_and_field(
        data, measured_directions(data, theta), chunk_obs=DEFAULT_CHUNK_OBS
    )
    rows = data.source_rows()[~consistent]
    return _Screened(rows.astype(np.int64), data.n_obs, data.n_frames, field_rad)


def _stats_chunk(data, theta0, theta, excluded) -> tuple[dict, tuple, tuple]:
    """Residual sums of one chunk's inliers at the nominal camera ``theta0`` (least-squares attitudes), added up over
    sub-chunks of the bundle's working size (``DEFAULT_CHUNK_OBS`` stars: small temporaries), and their interstar
    sums there and at the result ``theta`` (:func:`interstar_sums_of_directions`, in blocks of its own); the
    directions at the nominal are computed once for all three. The residuals at the result are the bundle's final
    pass's (:attr:`hostlink.calibration.bundle.ChunkedBundleResult.residual_sums`)."""
    fit = without_rows(data, excluded)
    b0 = pixels_to_unit(fit.x_px, fit.y_px, theta0)  # the measured directions at the nominal, for all three sums
    inter_before, inter_after = interstar_sums_of_directions(fit, [b0, pixels_to_unit(fit.x_px, fit.y_px, theta)])
    att0 = fitted_attitudes(fit, theta0, b0)  # all frames at once (an array operation per Newton step)
    before = None
    for f0, f1 in frame_chunks(fit.frame_starts, DEFAULT_CHUNK_OBS) or [(0, 0)]:
        b_sub = b0[fit.frame_starts[f0] : fit.frame_starts[f1]]
        part = residual_sums(frames_of(fit, f0, f1), theta0, att0[f0:f1], b=b_sub)
        before = part if before is None else merge_sums(before, part)
    return before, inter_before, inter_after


def sample_frames(source: ChunkSource, *frame_sets: np.ndarray) -> list[CalibrationData]:
    """For each array of global frame indices (sorted; counted through the chunks in order), those frames as one
    data set; every chunk is read once for all the sets."""
    parts: list[list[CalibrationData]] = [[] for _ in frame_sets]
    offset = 0
    for chunk in source:
        for frames, out in zip(frame_sets, parts, strict=True):
            local = frames[(frames >= offset) & (frames < offset + chunk.n_frames)] - offset
            if local.size:
                out.append(take_frames(chunk, local))
        offset += chunk.n_frames
    return [concatenate_data(p) for p in parts]


#: The least-squares warm start's samples: evenly spaced frames held in memory (~60 bytes a star, twice that while
#: gathered: ~120 MB for the largest at 20 stars per frame), each used when the session has more than twice as many
#: frames. Each level of 5-10x more frames starts the next a few of its standard deviations from its minimum, where
#: one Gauss-Newton step leaves ~1e-2 sigma (the step from s sigma leaves ~1.5e-3 s^2 here), so the full data take
#: two passes. The first level, 100 frames, is where the round from the nominal is cheapest (pass counts and
#: timings: docs/calibration.md).
WARM_LEVEL_FRAMES = (100, 1_000, 10_000, 50_000)


def warm_levels(source: ChunkSource, n_frames: int) -> tuple[CalibrationData, tuple[CalibrationData, ...]]:
    """The pre-pass sample (:func:`hostlink.calibration.robust.prepass_frames`) and the warm-start samples of
    :func:`hostlink.calibration.bundle.bundle_adjust_chunks` (coarse to fine: each of :data:`WARM_LEVEL_FRAMES` the
    session is more than twice as long as; none for a session up to twice the smallest), gathered in one read of
    the chunks."""
    levels = [prepass_frames(n_frames, k) for k in WARM_LEVEL_FRAMES if n_frames > 2 * k]
    samples = sample_frames(source, prepass_frames(n_frames), *levels)
    return samples[0], tuple(samples[1:])


def calibrate_chunks(
    source: ChunkSource,
    nominal: CameraParams,
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    progress: Callable[[dict], None] | None = None,
    run_pass: PassRunner = serial_pass,
    keep_data: CalibrationData | None = None,
) -> CalibrationOutcome:
    """The bundle calibration of :func:`calibrate` over the chunks of ``source`` (whole frames, each with its
    source rows), in memory O(K^2 + one chunk): the pre-pass on the evenly spaced frames gathered from the chunks,
    one voting pass, :func:`hostlink.calibration.bundle.bundle_adjust_chunks` (one pass per iteration, through
    ``run_pass``: in this process or on a Dask cluster, :mod:`hostlink.calibration.distributed`), and one pass for
    the residual statistics. :func:`calibrate` with ``method="bundle"`` is this on its data as one chunk
    (``keep_data``: then the outcome also carries the inlier data, their attitudes and the rejection masks).
    Raises ValueError as :func:`calibrate` does."""
    theta0 = nominal.model_vector(np.float64)
    sample, warm = warm_levels(source, source.n_frames())
    prepass = scale_and_parity_of_sample(sample, theta0)
    start = start_from_prepass(prepass, nominal, estimate is None or "f" in estimate)
    theta_start = start.model_vector(np.float64)
    screened = [_vote_chunk(c, theta_start) for c in source]
    voted = np.unique(np.concatenate([v.voted_rows for v in screened] + [np.zeros(0, np.int64)]))
    n_in = sum(v.n_stars for v in screened)
    m_in = sum(v.n_frames for v in screened)
    field_rad = max((v.field_rad for v in screened), default=float("nan"))
    if start is nominal and prepass.n_pairs and abs(prepass.scale - 1.0) > 0.03 and voted.size == n_in:
        raise ValueError(
            f"no star agrees with the catalogue at the nominal focal length, which the stars say is "
            f"{100 * (1 / prepass.scale - 1):+.1f} % off: estimate f"
        )
    held: list[dict] = []
    # a session more than twice as long as the smallest of WARM_LEVEL_FRAMES starts its least-squares round on samples
    res = _bundle_chunks(source, start, estimate or ESTIMATE_NAMES, noise_px, max_iter, progress, voted, run_pass, warm)
    if estimate is None:
        sigma_full = float(noise_px) if noise_px else res.sigma_estimated_px
        chosen, held = undetermined_parameters(res.normal, res.estimate, sigma_full, nominal, res.theta)
        if held:
            theta_restart = res.theta.copy()
            fixed = [ESTIMATE_NAMES.index(n) for n in ESTIMATE_NAMES if n not in chosen]
            theta_restart[fixed] = theta0[fixed]
            restart = nominal.with_model_vector(theta_restart)
            res = _bundle_chunks(source, restart, chosen, noise_px, max_iter, progress, voted, run_pass, ())
    dropped = np.union1d(voted, res.gated_rows)
    before = None
    inter_before, inter_after = (0.0, 0), (0.0, 0)
    for chunk in source:
        b, ib, ia = _stats_chunk(chunk, theta0, res.theta, dropped)
        before = b if before is None else merge_sums(before, b)
        inter_before = (inter_before[0] + ib[0], inter_before[1] + ib[1])
        inter_after = (inter_after[0] + ia[0], inter_after[1] + ia[1])
    rejected = {
        "voting": int(voted.size),
        "gating": int(res.gated_rows.size),
        "frames_dropped": int(m_in - res.n_frames),
        "total_stars": int(n_in - res.n_obs),
    }
    outcome = CalibrationOutcome(
        method="bundle",
        params=nominal.with_model_vector(res.theta),
        theta=res.theta,
        estimate=res.estimate,
        covariance=res.covariance,
        sigma_px=res.sigma_px,
        sigma_estimated_px=res.sigma_estimated_px,
        data=None,
        attitudes=None,
        before=stats_from_sums(before),
        after=stats_from_sums(res.residual_sums),
        interstar_before_rad=math.sqrt(inter_before[0] / inter_before[1]) if inter_before[1] else float("nan"),
        interstar_after_rad=math.sqrt(inter_after[0] / inter_after[1]) if inter_after[1] else float("nan"),
        rejected=rejected,
        degeneracies=degeneracies(res.normal, res.estimate, res.normal_u_diag),
        history=res.history,
        converged=res.converged,
        prepass=prepass_report(prepass, nominal, start),
        held=held,
        n_stars_used=res.n_obs,
        n_frames_used=res.n_frames,
        field_rad=field_rad,
    )
    if keep_data is not None:
        rows = keep_data.source_rows()
        outcome.voted_out = np.isin(rows, voted)
        outcome.gated = np.isin(rows, res.gated_rows)
        fit = without_rows(keep_data, dropped)
        outcome.data = fit
        outcome.attitudes = frame_attitudes(fit, res.theta, res.robust_sigma_px, BundleOptions.huber_k)
        outcome.before = residual_stats(fit, theta0, fitted_attitudes(fit, theta0))
        # the final pass's residuals, as on the chunked path; the clipped RMS needs them all: at the result
        e_len = np.linalg.norm(residuals(fit, res.theta, outcome.attitudes), axis=1)
        outcome.after["rms_px_clipped"] = clipped_rms(e_len)
    return outcome


def calibrate_session(
    session: Session,
    nominal: CameraParams,
    method: str = "bundle",
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    progress: Callable[[dict], None] | None = None,
    keep_failed: bool = False,
) -> tuple[CalibrationOutcome, SessionReferences]:
    """Batch ground calibration of a session from the ``nominal`` camera: its identified stars against their
    reference directions (:func:`hostlink.calibration.data.calibration_data_from_session`: file or Hipparcos; with
    ``site`` observed there, with ``weather`` refracted; ``dut1_s`` = UT1 - UTC [s]; with the time unknown J2000
    directions, :func:`time_unknown_note`), by ``method`` (:data:`METHODS`; ``estimate`` as in :func:`calibrate`),
    ``noise_px`` the centroid noise per axis [px] for the reported sigma (None: from the residuals), at most
    ``max_iter`` iterations; ``progress`` gets each iteration's record.

    Returns the outcome (with its ``rejected_stars`` and ``time_note``) and the references' report. A result that
    did not converge or rejected most stars (:meth:`CalibrationOutcome.failure`) raises :class:`UserError`, unless
    ``keep_failed``: then it is returned, and the caller must check ``outcome.failure()`` before using it. Also raises
    :class:`UserError` (one line) for bad options, a centroid off the nominal's detector, a session without enough
    identified stars, a mirrored image, a calibration that fails or a result that is not a usable parameter set."""
    if method not in METHODS:
        raise UserError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    if noise_px is not None and not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px {noise_px}: expected a positive number of pixels")
    if max_iter < 1:
        raise UserError(f"--max-iter {max_iter}: expected at least 1")
    if len(session) == 0:
        raise UserError("no star rows in the session")
    check_on_detector(session, nominal.image_size_px, "the session", "the nominal parameters")
    data, references = calibration_data_from_session(session, site, weather, dut1_s)
    try:
        outcome = calibrate(data, nominal, method, estimate, noise_px, max_iter, progress)
    except ValueError as exc:
        raise UserError(f"calibration failed: {exc}") from None
    _check_result(outcome, keep_failed)
    outcome.rejected_stars = rejected_stars(session, references, data, outcome)
    outcome.time_note = None if references.time_known else time_unknown_note(outcome)
    return outcome, references


def time_unknown_note(outcome: CalibrationOutcome) -> str:
    """The stated loss of a calibration against J2000 directions (the session gave no time): annual aberration
    (up to :data:`hostlink.sky.references.ABERRATION_MAX_RAD`) is left in the references. Its differential part over
    the field changes interstar angles by up to 20.5" x the angle [rad]: a scale error of up to 1.0e-4 in the focal
    length, and up to 20.5" x the field's largest pair angle in the directions."""
    field_rad = outcome.field_rad if outcome.data is None else max_pair_angle_rad(outcome.data)
    focal_px = float(outcome.theta[0])
    return (
        "time unknown: reference directions are J2000 catalogue places; precession and nutation are absorbed by "
        f"the per-frame attitudes, annual aberration is not: interstar angles may be off by up to "
        f'{ABERRATION_MAX_RAD * ARCSEC_PER_RAD * field_rad:.2g}" over this field ({math.degrees(field_rad):.3g} deg), '
        f"the focal length by up to {ABERRATION_MAX_RAD:.1e} relative ({ABERRATION_MAX_RAD * focal_px:.2g} px); "
        "proper motion since the directions' epoch (Hipparcos: J2000.0) is not applied either. If the date is "
        'known, give it as t_utc (any time that day: the aberration then errs by at most 0.18")'
    )


def _json_safe(value):
    """Non-finite floats -> None (JSON has no NaN or Infinity), through dicts and lists."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def result_extras(outcome: CalibrationOutcome, references: SessionReferences | None = None) -> dict:
    """The extra keys of the result file (INTERFACES.md: the parameter file plus extras), with ``references``
    (where the reference directions came from) when given; non-finite numbers as null. Also the rejected stars by
    reason and the time note when :func:`calibrate_session` set them, and ``failed`` (the reason) for a failed
    result kept on request."""
    extras = {
        "method": outcome.method,
        "estimated": list(outcome.estimate),
        "sigma": outcome.sigma(),
        "noise_px": outcome.sigma_px,
        "noise_estimated_px": outcome.sigma_estimated_px,
        "residuals": {"before": outcome.before, "after": outcome.after},
        "interstar_rms_rad": {"before": outcome.interstar_before_rad, "after": outcome.interstar_after_rad},
        "n_rejected": outcome.rejected,
        "degeneracies": outcome.degeneracies,
        "iterations": len(outcome.history),
        "converged": bool(outcome.converged),
        "held": outcome.held,
        "prepass": outcome.prepass,
    }
    if references is not None:
        extras["references"] = {
            "source": references.source,
            "refraction": references.refraction,
            "unidentified_rows": references.n_unidentified,
            "unknown_star_ids": int(references.unknown_rows.size),  # rows: in the --rejected file
            "time_known": references.time_known,
        }
    if outcome.rejected_stars is not None:
        extras["rejected_by_reason"] = outcome.rejected_stars.counts()
    if outcome.time_note:
        extras["time_unknown"] = outcome.time_note
    failure = outcome.failure()
    if failure:
        extras["failed"] = failure
    return _json_safe(extras)


@dataclass(frozen=True)
class ReferencesSummary:
    """Where the reference directions of a chunked session came from (the fields of
    :class:`hostlink.sky.references.SessionReferences` the result file reports), over all its chunks."""

    source: str
    refraction: str
    n_unidentified: int
    unknown_rows: np.ndarray  # session rows (counted through all files) whose star_id Hipparcos does not have
    time_known: bool


def spool_session(
    source,
    chunk_frames: int,
    nominal: CameraParams,
    directory: Path,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    on_frames: Callable[[int], None] | None = None,
) -> tuple[ChunkSource, ReferencesSummary]:
    """Read the session of ``source`` (paths, a glob, .csv or .parquet: :func:`hostlink.files.session.
    read_session_chunks`) ``chunk_frames`` frames at a time, turn each chunk into calibration data with its
    reference directions (:func:`hostlink.calibration.data.session_chunk_data`) and write it to ``directory``
    (:func:`hostlink.calibration.data.save_chunk`), so every later pass reads arrays at disk speed and computes no
    reference twice. Memory: one chunk. ``on_frames`` gets the number of frames read so far after each chunk (a
    progress bar). Raises UserError as :func:`calibrate_session` does."""
    from hostlink.files.session import read_session_chunks

    files: list[str] = []
    offset = 0
    n_identified = 0
    n_unidentified = 0
    unknown: list[np.ndarray] = []
    sources, refraction, time_known = set(), "none", True
    frames_read = 0
    for k, chunk in enumerate(read_session_chunks(source, chunk_frames)):
        frames_read += chunk.n_frames
        if on_frames is not None:
            on_frames(frames_read)
        check_on_detector(chunk, nominal.image_size_px, "the session", "the nominal parameters")
        n_identified += int(np.count_nonzero(chunk.star_id))
        data, refs = session_chunk_data(chunk, site, weather, dut1_s, offset)
        sources.add(refs.source)
        refraction = refs.refraction
        time_known &= refs.time_known
        n_unidentified += refs.n_unidentified
        unknown.append(refs.unknown_rows + offset)
        offset += len(chunk)
        if data.n_frames:
            path = directory / f"chunk{k:06d}{SPOOL_SUFFIX}"
            save_chunk(path, data)
            files.append(str(path))
    if offset == 0:
        raise UserError("no star rows in the session")
    if n_identified == 0:
        raise UserError("the session has no identified star (every star_id is 0)")
    if not files:
        raise UserError(f"no frame has at least {MIN_STARS_PER_FRAME} identified stars")
    summary = ReferencesSummary(
        "+".join(sorted(sources)), refraction, n_unidentified, np.concatenate(unknown), time_known
    )
    return ChunkSource(tuple(files), load_chunk, chunk_frame_count), summary


def calibrate_archive(
    source,
    nominal: CameraParams,
    chunk_frames: int | None = None,
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    progress: Callable[[dict], None] | None = None,
    keep_failed: bool = False,
    dask: str | None = None,
    dask_workers: int | None = None,
    spool_dir: str | Path | None = None,
    on_frames: Callable[[int], None] | None = None,
) -> tuple[CalibrationOutcome, ReferencesSummary]:
    """Bundle calibration of a session of any length in bounded memory: ``source`` is what
    :func:`hostlink.files.session.read_session_chunks` reads (a path, a glob, several files; CSV or Parquet),
    ``chunk_frames`` frames at a time (default :data:`hostlink.files.session.DEFAULT_CHUNK_FRAMES`), spooled to a
    temporary directory (in ``spool_dir`` when given) by :func:`spool_session`, then :func:`calibrate_chunks`:
    memory O(K^2 + one chunk), time linear in the frames. ``dask``: None (this process), ``"local"`` (a
    LocalCluster of ``dask_workers`` workers, default 2) or a scheduler address (``tcp://host:port``; its workers
    must see ``spool_dir``). ``on_frames``: frames read so far, after each chunk of the reading pass
    (:func:`spool_session`). Other arguments, the checks and the failure rule as :func:`calibrate_session`; the
    outcome has no in-memory data (``data`` None; its counts in ``n_stars_used``/``n_frames_used``)."""
    import tempfile

    from hostlink.files.session import DEFAULT_CHUNK_FRAMES

    if noise_px is not None and not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px {noise_px}: expected a positive number of pixels")
    if max_iter < 1:
        raise UserError(f"--max-iter {max_iter}: expected at least 1")
    chunk_frames = DEFAULT_CHUNK_FRAMES if chunk_frames is None else chunk_frames
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, int) or chunk_frames < 1:
        raise UserError(f"--chunk-frames {chunk_frames!r}: expected a whole number >= 1")
    with tempfile.TemporaryDirectory(prefix="hostlink-calibrate-", dir=spool_dir) as tmp:
        chunks, references = spool_session(source, chunk_frames, nominal, Path(tmp), site, weather, dut1_s, on_frames)
        try:
            if dask is None:
                outcome = calibrate_chunks(chunks, nominal, estimate, noise_px, max_iter, progress)
            else:
                from hostlink.calibration.distributed import DEFAULT_WORKERS, DaskPasses, dask_client

                with dask_client(dask, dask_workers or DEFAULT_WORKERS) as client:
                    outcome = calibrate_chunks(
                        chunks, nominal, estimate, noise_px, max_iter, progress, DaskPasses(client)
                    )
        except ValueError as exc:
            raise UserError(f"calibration failed: {exc}") from None
    _check_result(outcome, keep_failed)
    outcome.time_note = None if references.time_known else time_unknown_note(outcome)
    return outcome, references


def _check_result(outcome: CalibrationOutcome, keep_failed: bool) -> None:
    """Raise UserError for a failed result (unless ``keep_failed``) or unusable parameters."""
    failure = outcome.failure()
    if failure is not None and not keep_failed:
        raise UserError(f"calibration failed: {failure}")
    if failure is None:
        try:
            validate_params(outcome.params)
        except ParameterError as exc:
            raise UserError(f"the calibrated parameters are not usable ({exc}); check the nominal file") from None
