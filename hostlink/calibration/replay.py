"""Host driver of the onboard recursive calibration (docs/architecture.md: hostlink runs ``onboard`` logic unchanged).

:func:`replay_session` feeds a session, frame by frame, to :mod:`onboard.recursive` exactly as the sensor would
(identified stars only, the sensor's float32 or the host's float64 reference, or ``fixed``: the fixed-point front end
of :mod:`onboard.fixedpoint` for a sensor without an FPU, with its float32 filter) and collects a per-frame trace.
Each frame goes through :func:`onboard.firmware.estimator_update`, the entry the sensor's firmware runs.
:func:`replay_chunks` does the same over a session given in chunks of whole frames (read from disk by
:func:`hostlink.files.session.read_session_chunks`), handing each chunk's trace on as it goes, so its memory does not
grow with the session; :func:`replay_session` is it with one chunk.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session
from hostlink.files.trace import TRACE_COLUMNS
from hostlink.sky.references import session_references
from onboard import firmware, recursive
from onboard.fixedpoint import FixedRangeError
from onboard.params import DISTORTION_NAMES, ESTIMATE_NAMES, CameraParams, ParameterError, validate_params
from onboard.prior import prior_config, refined_mask, sigma_to_dict

PRECISIONS = ("float32", "float64", "fixed")
#: Which firmware runs the estimator: the Python model (onboard) or the C core (onboard/c).
FIRMWARE_CORES = ("python", "c")


@dataclass
class ReplayResult:
    params: CameraParams
    state: recursive.RecursiveState
    #: column name -> one value per frame (TRACE_COLUMNS); None when the trace was streamed, not kept
    trace: dict[str, list] | None
    #: where the prior came from: "file" (the nominal's sigma for every estimated parameter), "file+cold" or "cold"
    prior: str = "cold"
    frames: int = 0
    #: frames that updated the estimate (not skipped)
    frames_used: int = 0
    #: stars the estimator's gate rejected, over all frames
    rejected_stars: int = 0

    @property
    def n_frames(self) -> int:
        return self.frames


def precision_dtype(precision: str) -> np.dtype:
    """'float32' / 'float64' -> dtype of the estimator; 'fixed' -> float32 (its filter runs in soft float32 behind
    the integer front end; ``onboard.firmware.precision_dtype``). Anything else is a one-line UserError."""
    if precision not in PRECISIONS:
        raise UserError(f"--precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    return firmware.precision_dtype(precision)


def check_fixed_range(nominal: CameraParams) -> None:
    """The nominal set inside the fixed-point formats' proved range (``onboard.fixedpoint.fixed_camera``), or a
    one-line UserError: a fixed-point sensor could not run its estimator from it (replay and the emulator)."""
    from onboard import fixedpoint

    try:
        fixedpoint.fixed_camera(nominal.model_vector(np.float32), nominal.image_size_px)
    except fixedpoint.FixedRangeError as exc:
        raise UserError(f"--precision fixed: the nominal parameters are outside the fixed-point range: {exc}") from None


def replay_config(
    noise_px: float = 0.05,
    focal_walk_um: float = 0.0,
    drift_detect: bool = True,
    max_stars: int = 32,
    focal_length_mm: float | None = None,
) -> recursive.RecursiveConfig:
    """The onboard estimator's configuration: centroid noise per axis [px], focal-length random walk per frame
    (1-sigma [um]; 0 = static, with automatic drift detection unless ``drift_detect`` is False) and the most stars
    used per frame. ``focal_length_mm``: the nominal lens's, to which the walk the drift detector switches on is
    scaled (``onboard.recursive.drift_focal_mm_per_frame_for``, as the emulated sensor's; None: the default, the
    built-in 70 mm lens's). Out-of-range values are one-line :class:`UserError` s."""
    if not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px: must be a positive number, got {noise_px!r}")
    if not (math.isfinite(focal_walk_um) and focal_walk_um >= 0):
        raise UserError(f"--focal-walk-um: must be >= 0, got {focal_walk_um!r}")
    if max_stars < 3:
        raise UserError(f"--max-stars: must be >= 3, got {max_stars}")
    walk = [0.0] * len(ESTIMATE_NAMES)
    walk[0] = focal_walk_um / 1000.0
    drift_walk_mm = recursive.RecursiveConfig.drift_focal_mm_per_frame
    if focal_length_mm is not None:
        drift_walk_mm = recursive.drift_focal_mm_per_frame_for(focal_length_mm)
    return recursive.RecursiveConfig(
        max_stars=max_stars,
        centroid_noise_px=noise_px,
        process_noise=tuple(walk),
        drift_detect=drift_detect,
        drift_focal_mm_per_frame=drift_walk_mm,
    )


def replay_prior(
    file_sigma: np.ndarray, prior: str | None = None, source: str = "the nominal file"
) -> np.ndarray | None:
    """The prior the estimator starts from: the nominal file's ``sigma`` (10 values, NaN = unknown) for ``"file"``
    and by default, None (the cold-start prior) for ``"cold"``. ``"file"`` with no positive sigma is a UserError."""
    if prior not in (None, "file", "cold"):
        raise UserError(f"--prior {prior!r}: expected file or cold")
    if prior == "file" and not refined_mask(file_sigma).any():
        raise UserError(f"--prior file: {source} has no 'sigma' object with a positive 1-sigma")
    return None if prior == "cold" else file_sigma


def replay_session(
    session: Session,
    nominal: CameraParams,
    estimate: tuple[str, ...] = ESTIMATE_NAMES,
    config: recursive.RecursiveConfig | None = None,
    precision: str = "float32",
    on_frame: Callable[[int, recursive.FrameResult], None] | None = None,
    prior_sigma: np.ndarray | None = None,
) -> ReplayResult:
    """Run the onboard estimator over every frame of ``session`` (in memory) and return the final estimate and the
    whole trace: :func:`replay_chunks` with one chunk."""
    return replay_chunks([session], nominal, estimate, config, precision, on_frame, prior_sigma, keep_trace=True)


def replay_chunks(
    chunks: Iterable[Session],
    nominal: CameraParams,
    estimate: tuple[str, ...] = ESTIMATE_NAMES,
    config: recursive.RecursiveConfig | None = None,
    precision: str = "float32",
    on_frame: Callable[[int, recursive.FrameResult], None] | None = None,
    prior_sigma: np.ndarray | None = None,
    on_trace: Callable[[dict[str, list]], None] | None = None,
    keep_trace: bool = False,
    name: str = "the session",
    firmware_core: str = "python",
) -> ReplayResult:
    """Run the onboard estimator over every frame of a session given as consecutive chunks of whole frames (for
    instance :func:`hostlink.files.session.read_session_chunks`), in bounded memory: each chunk's trace (one row
    per frame, :data:`TRACE_COLUMNS`) goes to ``on_trace`` as it is done (a :class:`hostlink.files.trace.
    TraceWriter`), and is kept in the result only with ``keep_trace``. The estimate is the same, bit for bit, as
    over the whole session at once: the estimator sees the same frames in the same order.

    ``prior_sigma`` (10 values, ESTIMATE_NAMES order, parameter units; NaN/0 = unknown) is the nominal's 1-sigma:
    the estimator starts from it exactly as the sensor does after an upload (``onboard.prior.prior_config``).
    Reference directions: :func:`hostlink.sky.references.session_references` (the file's ra_deg/dec_deg, or the
    Hipparcos apparent place as the sensor computes it from its onboard catalogue); unidentified stars are not
    used. ``on_frame(k, result)`` is called after frame k (counted from 0 over all chunks). A session without
    frames ("NAME: no frames", ``name`` the session's), one where no frame could update the estimate, a diverged
    or unusable estimate is a one-line :class:`UserError`. ``firmware_core`` "c" runs each frame through the C
    firmware core (onboard/c, built with the machine's compiler: ``hostlink.portkit.estimator_c.stepper``) instead
    of the Python model; float32 and fixed only."""
    dtype = precision_dtype(precision)
    if firmware_core not in FIRMWARE_CORES:
        raise UserError(f"--firmware: expected one of {', '.join(FIRMWARE_CORES)}, got {firmware_core!r}")
    if firmware_core == "c" and precision == "float64":
        raise UserError("--firmware c: the C core runs float32 or fixed (float64 is the host's Python reference)")
    try:
        config = prior_config(config, nominal, prior_sigma, estimate)
        state = recursive.create(nominal, estimate, config, dtype)
    except ValueError as exc:
        raise UserError(f"estimator configuration: {exc}") from None
    if precision == "fixed":
        check_fixed_range(nominal)
    step = firmware.estimator_update
    if firmware_core == "c":
        from hostlink.portkit import estimator_c

        try:
            step = estimator_c.stepper(state)
        except ValueError as exc:
            raise UserError(f"--firmware c: {exc}") from None
    kept: dict[str, list] = {c: [] for c in TRACE_COLUMNS}
    tally = _Tally()
    rows_before = 0
    for session in chunks:
        trace = _replay_chunk(state, session, precision, on_frame, tally, rows_before, step)
        rows_before += len(session)
        if on_trace is not None:
            on_trace(trace)
        if keep_trace:
            for name, values in kept.items():
                values.extend(trace[name])
    if tally.frames == 0:
        raise UserError(f"{name}: no frames")
    refined = refined_mask(prior_sigma)[state.idx]
    prior = "file" if np.all(refined) else ("file+cold" if np.any(refined) else "cold")
    if state.updates == 0:
        raise UserError("no frame had 3 or more identified, consistent stars; nothing estimated")
    params = recursive.current_params(state)
    _check_diverged(tally.first_nonfinite_frame)
    check_usable(params)
    return ReplayResult(
        params=params,
        state=state,
        trace=kept if keep_trace else None,
        prior=prior,
        frames=tally.frames,
        frames_used=tally.frames_used,
        rejected_stars=tally.rejected_stars,
    )


@dataclass
class _Tally:
    """What the result reports of the frames replayed so far, kept as they go (the trace need not be kept)."""

    frames: int = 0
    frames_used: int = 0
    rejected_stars: int = 0
    first_nonfinite_frame: int | None = None


def _replay_chunk(
    state, session: Session, precision: str, on_frame, tally: _Tally, rows_before: int, step=firmware.estimator_update
) -> dict[str, list]:
    """The frames of one chunk through the estimator; returns the chunk's trace and counts its frames in ``tally``."""
    references = session_references(session, first_row=rows_before)
    r_all, identified_all = references.r, references.usable
    trace: dict[str, list] = {c: [] for c in TRACE_COLUMNS}
    for rows in session.frame_slices():
        args = (state, session.x_px[rows], session.y_px[rows], r_all[rows], identified_all[rows], precision)
        try:
            res = step(*args)  # what the sensor runs on each frame, in its precision (Python model or C core)
        except FixedRangeError as exc:
            frame = int(session.frame[rows.start])
            raise UserError(
                f"--precision fixed: frame {frame}: the estimate left the fixed-point range: {exc}"
            ) from None
        _append_trace(trace, state, res, int(session.frame[rows.start]), str(session.t_utc[rows.start]))
        if on_frame is not None:
            on_frame(tally.frames, res)
        tally.frames += 1
        tally.frames_used += not res.skipped
        tally.rejected_stars += len(res.rejected_stars)
    if tally.first_nonfinite_frame is None:
        focal = np.asarray(trace["focal_length_mm"], dtype=np.float64)
        if not np.all(np.isfinite(focal)):
            tally.first_nonfinite_frame = int(trace["frame"][int(np.argmax(~np.isfinite(focal)))])
    return trace


def check_estimate(params: CameraParams, trace: dict[str, list]) -> None:
    """A diverged or unusable estimate is a one-line error naming the first bad frame, never a NaN file."""
    focal = np.asarray(trace["focal_length_mm"], dtype=np.float64)
    bad = ~np.isfinite(focal)
    _check_diverged(int(trace["frame"][int(np.argmax(bad))]) if np.any(bad) else None)
    check_usable(params)


def _check_diverged(first_nonfinite_frame: int | None) -> None:
    if first_nonfinite_frame is not None:
        raise UserError(
            f"the onboard estimator diverged (non-finite estimate at frame {first_nonfinite_frame}); check the "
            "nominal parameters and --noise-px"
        )


def check_usable(params: CameraParams) -> None:
    """The final estimate a valid parameter set, or a one-line UserError."""
    try:
        validate_params(params)
    except ParameterError as exc:
        raise UserError(f"the final estimate is not a usable parameter set: {exc}") from None


def _append_trace(trace: dict[str, list], state, res: recursive.FrameResult, frame: int, t_utc: str) -> None:
    theta = recursive.state_vector(state)
    sd = np.sqrt(np.diag(recursive.covariance(state)))
    sig = dict.fromkeys(ESTIMATE_NAMES, float("nan"))
    for name, v in zip(state.names, sd, strict=True):
        sig[name] = float(v)
    pitch = state.nominal.pixel_pitch_um
    trace["frame"].append(frame)
    trace["t_utc"].append(t_utc)
    trace["focal_length_mm"].append(theta[0] * pitch / 1000.0)
    trace["x0_px"].append(theta[1])
    trace["y0_px"].append(theta[2])
    for k, name in enumerate(DISTORTION_NAMES):
        trace[name].append(theta[3 + k])
    trace["sigma_f_mm"].append(sig["f"] * pitch / 1000.0)
    trace["sigma_x0_px"].append(sig["x0"])
    trace["sigma_y0_px"].append(sig["y0"])
    trace["n_stars"].append(res.n_stars)
    trace["n_used"].append(res.n_used)
    trace["n_rejected_stars"].append(len(res.rejected_stars))
    trace["n_pairs"].append(res.n_pairs)
    trace["iterations"].append(res.iterations)
    trace["nis"].append(res.nis)
    trace["drift_on"].append(int(state.drift_on))
    trace["skipped"].append(res.skipped)


def estimate_extras(result: ReplayResult, precision: str) -> dict:
    """Extra keys of ESTIMATE.json: sigma of each estimated parameter, method, precision, the prior it started from
    (``file``: the nominal's sigma for every estimated parameter; ``file+cold``: for some; ``cold``) and frame
    statistics; ``status`` / ``status_reason`` (:mod:`hostlink.calibration.status`)."""
    from hostlink.calibration.status import replay_status

    state = result.state
    return {
        "sigma": estimate_sigma_json(state),
        "method": "onboard-recursive-ud",
        "precision": precision,
        "prior": result.prior,
        "burn_in_frames": int(state.config.burn_in_frames),
        "estimated": list(state.names),
        "frames": result.n_frames,
        "frames_used": result.frames_used,
        "rejected_stars": result.rejected_stars,
        "focal_drift_detected_frame": state.drift_frame if state.drift_on else None,
        **replay_status(state),  # issue 31: upload refuses an estimate that has not converged
    }


def estimate_sigma_json(state) -> dict:
    """The estimate's 1-sigma in the parameter file's layout (as ``hostlink calibrate`` writes it, and as
    ``hostlink upload`` sends it): estimated parameters get their sigma, the others are null and listed in ``fixed``."""
    values = np.full(len(ESTIMATE_NAMES), np.nan)
    for name, value in recursive.sigma(state).items():
        values[ESTIMATE_NAMES.index(name)] = value
    out = sigma_to_dict(values) or {}
    out["fixed"] = [n for n in ESTIMATE_NAMES if n not in state.names]
    return out
