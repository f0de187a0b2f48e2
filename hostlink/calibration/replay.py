"""Host driver of the onboard recursive calibration (ARCHITECTURE.md: hostlink runs ``onboard`` logic unchanged).

:func:`replay_session` feeds a session, frame by frame, to :mod:`onboard.recursive` exactly as the sensor would
(identified stars only, the sensor's float32 or the host's float64 reference, or ``fixed``: the fixed-point front end
of :mod:`onboard.fixedpoint` for a sensor without an FPU, with its float32 filter) and collects a per-frame trace. It
is shared by ``hostlink replay`` and the emulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session
from hostlink.files.trace import TRACE_COLUMNS
from hostlink.sky.references import session_references
from onboard import recursive
from onboard.params import DISTORTION_NAMES, ESTIMATE_NAMES, CameraParams, ParameterError, validate_params
from onboard.prior import prior_config, refined_mask, sigma_to_dict

PRECISIONS = ("float32", "float64", "fixed")


@dataclass
class ReplayResult:
    params: CameraParams
    state: recursive.RecursiveState
    trace: dict[str, list]  # column name -> one value per frame (TRACE_COLUMNS)
    #: where the prior came from: "file" (the nominal's sigma for every estimated parameter), "file+cold" or "cold"
    prior: str = "cold"

    @property
    def n_frames(self) -> int:
        return len(self.trace["frame"])


def precision_dtype(precision: str) -> np.dtype:
    """'float32' / 'float64' -> dtype of the estimator; 'fixed' -> float32 (its filter runs in soft float32 behind
    the integer front end). Anything else is a one-line UserError."""
    if precision not in PRECISIONS:
        raise UserError(f"--precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    return np.dtype(np.float32) if precision == "fixed" else np.dtype(precision)


@dataclass
class _FixedInputs:
    """The session as a fixed-point sensor receives it: centroids in the wire's 2^-10 px steps, catalogue unit
    vectors in Q30, and the mask of stars the front end can take (identified and on the detector)."""

    x_steps: np.ndarray
    y_steps: np.ndarray
    r_q30: np.ndarray
    usable: np.ndarray


def _fixed_inputs(session: Session, nominal: CameraParams, r_all: np.ndarray, identified: np.ndarray) -> _FixedInputs:
    from onboard import fixedpoint
    from protocol.messages import quantise_px

    try:
        fixedpoint.fixed_camera(nominal.model_vector(np.float32), nominal.image_size_px)
    except fixedpoint.FixedRangeError as exc:
        raise UserError(f"--precision fixed: the nominal parameters are outside the fixed-point range: {exc}") from None
    x_steps = quantise_px(session.x_px)
    y_steps = quantise_px(session.y_px)
    r_q30 = fixedpoint.quantise_unit_q30(np.where(np.isfinite(r_all), r_all, 0.0))
    usable = identified & fixedpoint.on_detector(x_steps, y_steps, nominal.image_size_px)
    return _FixedInputs(x_steps, y_steps, r_q30, usable)


def replay_config(
    noise_px: float = 0.05, focal_walk_um: float = 0.0, drift_detect: bool = True, max_stars: int = 32
) -> recursive.RecursiveConfig:
    """The onboard estimator's configuration: centroid noise per axis [px], focal-length random walk per frame
    (1-sigma [um]; 0 = static, with automatic drift detection unless ``drift_detect`` is False) and the most stars
    used per frame. Out-of-range values are one-line :class:`UserError` s."""
    if not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px: must be a positive number, got {noise_px!r}")
    if not (math.isfinite(focal_walk_um) and focal_walk_um >= 0):
        raise UserError(f"--focal-walk-um: must be >= 0, got {focal_walk_um!r}")
    if max_stars < 3:
        raise UserError(f"--max-stars: must be >= 3, got {max_stars}")
    walk = [0.0] * len(ESTIMATE_NAMES)
    walk[0] = focal_walk_um / 1000.0
    return recursive.RecursiveConfig(
        max_stars=max_stars, centroid_noise_px=noise_px, process_noise=tuple(walk), drift_detect=drift_detect
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
    """Run the onboard estimator over every frame of ``session`` and return the final estimate and the trace.
    ``prior_sigma`` (10 values, ESTIMATE_NAMES order, parameter units; NaN/0 = unknown) is the nominal's 1-sigma:
    the estimator starts from it exactly as the sensor does after an upload (``onboard.prior.prior_config``).
    Reference directions: :func:`hostlink.sky.references.session_references` (the file's ra_deg/dec_deg, or the
    Hipparcos apparent place as the sensor computes it from its onboard catalogue); unidentified stars are not
    used."""
    dtype = precision_dtype(precision)
    try:
        config = prior_config(config, nominal, prior_sigma, estimate)
        state = recursive.create(nominal, estimate, config, dtype)
    except ValueError as exc:
        raise UserError(f"estimator configuration: {exc}") from None
    references = session_references(session)
    r_all, identified_all = references.r, references.usable
    fixed = _fixed_inputs(session, nominal, r_all, identified_all) if precision == "fixed" else None
    trace: dict[str, list] = {c: [] for c in TRACE_COLUMNS}
    for k, rows in enumerate(session.frame_slices()):
        if fixed is None:
            res = recursive.update(state, session.x_px[rows], session.y_px[rows], r_all[rows], identified_all[rows])
        else:
            res = _update_fixed(state, fixed, rows, r_all, nominal, int(session.frame[rows.start]))
        _append_trace(trace, state, res, int(session.frame[rows.start]), str(session.t_utc[rows.start]))
        if on_frame is not None:
            on_frame(k, res)
    refined = refined_mask(prior_sigma)[state.idx]
    prior = "file" if np.all(refined) else ("file+cold" if np.any(refined) else "cold")
    if state.updates == 0:
        raise UserError("no frame had 3 or more identified, consistent stars; nothing estimated")
    params = recursive.current_params(state)
    check_estimate(params, trace)
    return ReplayResult(params=params, state=state, trace=trace, prior=prior)


def check_estimate(params: CameraParams, trace: dict[str, list]) -> None:
    """A diverged or unusable estimate is a one-line error naming the first bad frame, never a NaN file."""
    focal = np.asarray(trace["focal_length_mm"], dtype=np.float64)
    bad = ~np.isfinite(focal)
    if np.any(bad):
        frame = trace["frame"][int(np.argmax(bad))]
        raise UserError(
            f"the onboard estimator diverged (non-finite estimate at frame {frame}); check the nominal "
            "parameters and --noise-px"
        )
    try:
        validate_params(params)
    except ParameterError as exc:
        raise UserError(f"the final estimate is not a usable parameter set: {exc}") from None


def _update_fixed(state, fixed: _FixedInputs, rows: slice, r_all, nominal: CameraParams, frame: int):
    """One frame through the fixed-point front end; the float32 Jacobians see the same (wire-rounded) centroids."""
    from onboard import fixedpoint
    from protocol.messages import dequantise_px

    front = fixedpoint.FixedFrame(fixed.x_steps[rows], fixed.y_steps[rows], fixed.r_q30[rows], nominal.image_size_px)
    try:
        return recursive.update(
            state,
            dequantise_px(fixed.x_steps[rows]),
            dequantise_px(fixed.y_steps[rows]),
            r_all[rows],
            fixed.usable[rows],
            front_end=front,
        )
    except fixedpoint.FixedRangeError as exc:
        raise UserError(f"--precision fixed: frame {frame}: the estimate left the fixed-point range: {exc}") from None


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
    statistics."""
    state = result.state
    used = sum(1 for s in result.trace["skipped"] if not s)
    return {
        "sigma": estimate_sigma_json(state),
        "method": "onboard-recursive-ud",
        "precision": precision,
        "prior": result.prior,
        "burn_in_frames": int(state.config.burn_in_frames),
        "estimated": list(state.names),
        "frames": result.n_frames,
        "frames_used": used,
        "rejected_stars": int(sum(result.trace["n_rejected_stars"])),
        "focal_drift_detected_frame": state.drift_frame if state.drift_on else None,
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
