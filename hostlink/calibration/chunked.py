"""The bundle calibration run over chunks of frames: the one driver of the default method, for a session in memory
(one chunk) or read from files of any length (spooled chunks), in memory O(K^2 + one chunk)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from hostlink.calibration.bundle import BundleOptions, ChunkedBundleResult, bundle_adjust_chunks
from hostlink.calibration.data import (
    MIN_STARS_PER_FRAME,
    SPOOL_SUFFIX,
    CalibrationData,
    chunk_frame_count,
    concatenate_data,
    frame_chunks,
    load_chunk,
    measured_directions,
    save_chunk,
    session_chunk_data,
    take_frames,
)
from hostlink.calibration.floorfit import fit_with_floor, noise_outcome, radial_allowed
from hostlink.calibration.mirror import with_mirror
from hostlink.calibration.model import DEFAULT_CHUNK_OBS, residuals
from hostlink.calibration.noisefloor import NoiseModel, floored_source, with_floor
from hostlink.calibration.outcome import (
    CalibrationOutcome,
    ReferencesSummary,
    check_focal_scale,
    check_result,
    check_run_options,
    prepass_report,
    rejected_counts,
    start_from_prepass,
    time_unknown_note,
)
from hostlink.calibration.passes import PassRunner, frame_attitudes, serial_pass
from hostlink.calibration.report import (
    clipped_rms,
    fitted_attitudes,
    interstar_sums_of_directions,
    merge_sums,
    residual_stats,
    residual_sums,
    stats_from_sums,
    undetermined_parameters,
)
from hostlink.calibration.robust import (
    consistent_stars_and_field,
    prepass_frames,
    scale_and_parity_of_sample,
)
from hostlink.calibration.source import ChunkSource, frames_of, without_rows
from hostlink.errors import UserError
from hostlink.files.session import check_on_detector
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams
from onboard.site import Site, Weather


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
    noise_model: str = "auto",
    mirror_fit: bool = True,
) -> CalibrationOutcome:
    """The bundle calibration of :func:`hostlink.calibration.run.calibrate` over the chunks of ``source`` (whole
    frames, each with its source rows), in memory O(K^2 + one chunk): the pre-pass on the evenly spaced frames
    gathered from the chunks, one voting pass (:func:`_screen`), the fit (:func:`_fit`: through ``run_pass``, in
    this process or on a Dask cluster, :mod:`hostlink.calibration.distributed`), and one pass for the residual
    statistics (:func:`_statistics`). Stars of given noise (the session's ``sigma_px``) are each whitened by it;
    the outcome's ``noise_scale`` is then the noise the residuals show relative to the given one (1 when it is
    right), and the covariance is scaled by its square. The in-memory calibration is this on its data as one chunk
    (``keep_data``: then the outcome also carries the inlier data, their attitudes and the rejection masks).
    ``noise_model``: "auto" (the floor constant or radial as the data choose) or "constant"; ``mirror_fit``: as
    :attr:`BundleOptions.mirror_fit`. Raises ValueError as :func:`hostlink.calibration.run.calibrate` does."""
    radial = radial_allowed(noise_model)  # an unknown model refused before any pass, with sigma_px or not
    theta0 = nominal.model_vector(np.float64)
    sample, warm = warm_levels(source, source.n_frames())
    weighted = sample.sigma_px is not None
    if weighted and noise_px:
        raise ValueError(
            "the session's sigma_px column and --noise-px both give the centroid noise: drop --noise-px (the fit "
            "reports the noise it finds relative to sigma_px)"
        )
    prepass = scale_and_parity_of_sample(sample, theta0)
    start = start_from_prepass(prepass, nominal, estimate is None or "f" in estimate)
    screened = _screen(source, start.model_vector(np.float64))
    voted = screened.voted_rows
    check_focal_scale(prepass, start is nominal, voted.size == screened.n_stars)
    options = BundleOptions(
        estimate=estimate or ESTIMATE_NAMES,
        noise_px=noise_px,
        max_iter=max_iter,
        progress=progress,
        mirror_fit=mirror_fit,
    )
    fit = partial(fit_with_floor, _fit, radial=radial) if weighted else _fit
    res, held, *floor = fit(source, nominal, start, options, estimate is None, voted, run_pass, warm)
    noise, comps = floor[0] if floor else (NoiseModel(), None)  # the statistics and attitudes weighted as the fit
    source = floored_source(source, noise)
    keep_data = None if keep_data is None else with_floor(keep_data, noise)  # outcome.data: the noise used
    dropped = np.union1d(voted, res.gated_rows)
    before, inter_before_rad, inter_after_rad = _statistics(source, theta0, res.theta, dropped)
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
        before=before,
        after=stats_from_sums(res.residual_sums),
        interstar_before_rad=inter_before_rad,
        interstar_after_rad=inter_after_rad,
        rejected=_rejected(screened, res),
        degeneracies=with_mirror(source, nominal, res, options, voted, run_pass),
        history=res.history,
        converged=res.converged,
        prepass=prepass_report(prepass, nominal, start),
        held=held,
        n_stars_used=res.n_obs,
        n_frames_used=res.n_frames,
        field_rad=screened.field_rad,
        status=res.status.value,
        **(noise_outcome(res.sigma_estimated_px, noise, comps) if weighted else {}),
    )
    if keep_data is not None:
        _add_in_memory_results(outcome, keep_data, voted, res, theta0)
    return outcome


def _screen(source: ChunkSource, theta: np.ndarray) -> _Screened:
    """The voting pass over every chunk at the camera ``theta``: the rejected source rows (sorted), the stars and
    frames of the input and the widest field of a frame."""
    screened = [_vote_chunk(c, theta) for c in source]
    return _Screened(
        np.unique(np.concatenate([v.voted_rows for v in screened] + [np.zeros(0, np.int64)])),
        sum(v.n_stars for v in screened),
        sum(v.n_frames for v in screened),
        max((v.field_rad for v in screened), default=float("nan")),
    )


def _rejected(screened: _Screened, res: ChunkedBundleResult) -> dict[str, int]:
    """The outcome's ``rejected``: the stars voted out, the stars gated out, and the frames and stars the fit did not
    use of the input."""
    return {
        "voting": int(screened.voted_rows.size),
        "gating": int(res.gated_rows.size),
        "frames_dropped": int(screened.n_frames - res.n_frames),
        "total_stars": int(screened.n_stars - res.n_obs),
    }


def _fit(
    source: ChunkSource,
    nominal: CameraParams,
    start: CameraParams,
    options: BundleOptions,
    choose: bool,
    voted: np.ndarray,
    run_pass: PassRunner,
    warm: tuple[CalibrationData, ...],
) -> tuple[ChunkedBundleResult, list[dict]]:
    """The bundle fit from ``start`` without the ``voted`` rows (a session more than twice as long as the smallest
    of :data:`WARM_LEVEL_FRAMES` starts its least-squares round on the ``warm`` samples); with ``choose`` (no
    estimate given), then again without the parameters the data cannot determine
    (:func:`hostlink.calibration.report.undetermined_parameters`), which are held at nominal. Returns the result and
    the held parameters' records."""
    res = bundle_adjust_chunks(source, start, options, voted, run_pass, warm)
    if not choose:
        return res, []
    sigma_full = float(options.noise_px) if options.noise_px else res.sigma_estimated_px
    chosen, held = undetermined_parameters(res.normal, res.estimate, sigma_full, nominal, res.theta)
    if held:
        theta_restart = res.theta.copy()
        fixed = [ESTIMATE_NAMES.index(n) for n in ESTIMATE_NAMES if n not in chosen]
        theta_restart[fixed] = nominal.model_vector(np.float64)[fixed]
        restart = nominal.with_model_vector(theta_restart)
        res = bundle_adjust_chunks(source, restart, replace(options, estimate=chosen), voted, run_pass, ())
    return res, held


def _statistics(
    source: ChunkSource, theta0: np.ndarray, theta: np.ndarray, dropped: np.ndarray
) -> tuple[dict, float, float]:
    """One pass over the chunks for the statistics of the inliers (the stars not ``dropped``): the residual
    statistics at the nominal ``theta0`` and the interstar RMS [rad] there and at the result ``theta``."""
    before = None
    inter_before, inter_after = (0.0, 0), (0.0, 0)
    for chunk in source:
        b, ib, ia = _stats_chunk(chunk, theta0, theta, dropped)
        before = b if before is None else merge_sums(before, b)
        inter_before = (inter_before[0] + ib[0], inter_before[1] + ib[1])
        inter_after = (inter_after[0] + ia[0], inter_after[1] + ia[1])

    def rms(sums: tuple[float, int]) -> float:
        return math.sqrt(sums[0] / sums[1]) if sums[1] else float("nan")

    return stats_from_sums(before), rms(inter_before), rms(inter_after)


def _add_in_memory_results(
    outcome: CalibrationOutcome,
    data: CalibrationData,
    voted: np.ndarray,
    res: ChunkedBundleResult,
    theta0: np.ndarray,
) -> None:
    """What a session held in memory adds to the outcome: the rejection masks, the inlier data and their
    attitudes, the exact statistics at the nominal and the clipped RMS at the result (it needs every residual)."""
    rows = data.source_rows()
    outcome.voted_out = np.isin(rows, voted)
    outcome.gated = np.isin(rows, res.gated_rows)
    fit = without_rows(data, np.union1d(voted, res.gated_rows))
    outcome.data = fit
    outcome.attitudes = frame_attitudes(fit, res.theta, res.robust_sigma_px, BundleOptions.huber_k)
    outcome.before = residual_stats(fit, theta0, fitted_attitudes(fit, theta0))
    # the final pass's residuals, as on the chunked path; the clipped RMS needs them all: at the result
    e_len = np.linalg.norm(residuals(fit, res.theta, outcome.attitudes), axis=1)
    outcome.after["rms_px_clipped"] = clipped_rms(e_len)


def spool_session(
    source,
    chunk_frames: int,
    nominal: CameraParams,
    directory: Path,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    on_frames: Callable[[int], None] | None = None,
    on_rows: Callable[[int], None] | None = None,
) -> tuple[ChunkSource, ReferencesSummary]:
    """Read the session of ``source`` (paths, a glob, .csv or .parquet: :func:`hostlink.files.session.
    read_session_chunks`) ``chunk_frames`` frames at a time, turn each chunk into calibration data with its
    reference directions (:func:`hostlink.calibration.data.session_chunk_data`) and write it to ``directory``
    (:func:`hostlink.calibration.data.save_chunk`), so every later pass reads arrays at disk speed and computes no
    reference twice. Memory: one chunk. ``on_frames`` gets the number of frames read so far after each chunk (a
    progress bar), ``on_rows`` the number of rows (stars) read. Raises UserError as :func:`calibrate_session` does."""
    from hostlink.files.session import read_session_chunks

    files: list[str] = []
    offset = 0
    n_identified = 0
    n_unidentified = 0
    n_few = 0
    unknown: list[np.ndarray] = []
    sources, refraction, time_known = set(), "none", True
    frames_read = 0
    for k, chunk in enumerate(read_session_chunks(source, chunk_frames)):
        frames_read += chunk.n_frames
        if on_frames is not None:
            on_frames(frames_read)
        if on_rows is not None:
            on_rows(offset + len(chunk))
        check_on_detector(chunk, nominal.image_size_px, "the session", "the nominal parameters")
        n_identified += int(np.count_nonzero(chunk.star_id))
        data, refs = session_chunk_data(chunk, site, weather, dut1_s, offset)
        n_few += int(np.count_nonzero(refs.usable)) - data.n_obs
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
        "+".join(sorted(sources)), refraction, n_unidentified, np.concatenate(unknown), time_known, n_few
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
    on_rows: Callable[[int], None] | None = None,
    noise_model: str = "auto",
) -> tuple[CalibrationOutcome, ReferencesSummary]:
    """Bundle calibration of a session of any length in bounded memory: ``source`` is what
    :func:`hostlink.files.session.read_session_chunks` reads (a path, a glob, several files; CSV or Parquet),
    ``chunk_frames`` frames at a time (default :data:`hostlink.files.session.DEFAULT_CHUNK_FRAMES`), spooled to a
    temporary directory (in ``spool_dir`` when given) by :func:`spool_session`, then :func:`calibrate_chunks`:
    memory O(K^2 + one chunk), time linear in the frames. ``dask``: None (this process), ``"local"`` (a
    LocalCluster of ``dask_workers`` workers, default 2) or a scheduler address (``tcp://host:port``; its workers
    must see ``spool_dir``). ``on_frames``: frames read so far, after each chunk of the reading pass
    (:func:`spool_session`); ``on_rows``: rows read so far (against :func:`estimated_session_rows`);
    ``noise_model`` as in :func:`hostlink.calibration.run.calibrate`. Other
    arguments, the checks and the failure rule as :func:`hostlink.calibration.run.calibrate_session`; the outcome
    has no in-memory data (``data`` None; its counts in ``n_stars_used``/``n_frames_used``), and its rejected stars
    counted by reason (:func:`hostlink.calibration.outcome.rejected_counts`)."""
    import tempfile

    from hostlink.files.session import DEFAULT_CHUNK_FRAMES

    check_run_options(noise_px, max_iter, noise_model)
    chunk_frames = DEFAULT_CHUNK_FRAMES if chunk_frames is None else chunk_frames
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, int) or chunk_frames < 1:
        raise UserError(f"--chunk-frames {chunk_frames!r}: expected a whole number >= 1")
    try:
        spool = tempfile.TemporaryDirectory(prefix="hostlink-calibrate-", dir=spool_dir)
    except OSError as exc:  # a --spool-dir that is no folder, or one (or the system's temporary folder) not writable
        where = spool_dir if spool_dir is not None else tempfile.gettempdir()
        raise UserError(
            f"{where}: cannot make the calibration's spool folder there ({exc.strerror or exc}); --spool-dir picks "
            "another"
        ) from None
    with spool as tmp:
        chunks, references = spool_session(
            source, chunk_frames, nominal, Path(tmp), site, weather, dut1_s, on_frames, on_rows
        )
        try:
            if dask is None:
                outcome = calibrate_chunks(
                    chunks, nominal, estimate, noise_px, max_iter, progress, noise_model=noise_model
                )
            else:
                from hostlink.calibration.distributed import DEFAULT_WORKERS, DaskPasses, dask_client

                with dask_client(dask, dask_workers or DEFAULT_WORKERS) as client:
                    passes = DaskPasses(client)
                    outcome = calibrate_chunks(
                        chunks, nominal, estimate, noise_px, max_iter, progress, passes, noise_model=noise_model
                    )
        except ValueError as exc:
            raise UserError(f"calibration failed: {exc}") from None
    outcome.rejected_by_reason = rejected_counts(outcome, references)
    check_result(outcome, keep_failed)
    outcome.time_note = None if references.time_known else time_unknown_note(outcome)
    return outcome, references


#: Bytes of a CSV session's head read to measure its mean line length (:func:`estimated_session_rows`): a few
#: thousand lines, whose mean length is that of the file to a few per cent when its columns have a fixed format.
HEAD_SAMPLE_BYTES = 1 << 18


def estimated_session_rows(source) -> int | None:
    """The number of star rows of the session files of ``source`` (as :func:`hostlink.files.session.session_paths`
    names them), for a progress bar's total: a Parquet file's from its metadata (exact), a CSV file's from its size
    over the mean length of the lines of its first :data:`HEAD_SAMPLE_BYTES` (an estimate). None when a file cannot
    be sized (missing, unreadable: the reader then says why)."""
    from hostlink.files.session import session_paths

    total = 0
    try:
        for path in session_paths(source):
            if path.suffix.lower() == ".parquet":
                import pyarrow.parquet as pq

                total += int(pq.ParquetFile(path).metadata.num_rows)
                continue
            with open(path, "rb") as f:
                head = f.read(HEAD_SAMPLE_BYTES)
            lines = head.count(b"\n")
            if lines < 2:
                total += max(lines - 1, 0)
                continue
            header = head.index(b"\n") + 1
            size = path.stat().st_size
            mean = (head.rindex(b"\n") + 1 - header) / (lines - 1)
            total += round((size - header) / mean)
    except (OSError, ValueError, UserError, ImportError):
        return None
    return total
