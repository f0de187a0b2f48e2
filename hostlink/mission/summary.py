"""What a bench run produced (:class:`BenchRun`) and its report: ``summary.json``'s content and the terminal table.

Pure functions of the run's data: nothing here touches a link, a process or the clock.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hostlink.calibration.bundle import ARCSEC_PER_RAD
from hostlink.calibration.report import fitted_attitudes
from hostlink.mission.config import BenchConfig, drift_amplitude_um, drift_first_frame
from onboard.params import CameraParams

if TYPE_CHECKING:  # annotations only
    from hostlink.calibration.data import CalibrationData
    from hostlink.calibration.run import CalibrationOutcome
    from hostlink.links.operations import ActiveParams, UploadResult
    from hostlink.sky.references import SessionReferences
    from hostlink.sky.simulate import SimResult
    from protocol.messages import Estimate


@dataclass
class Phase:
    """One step of the run: its name, wall-clock duration [s] and a one-line detail for the report."""

    name: str
    seconds: float
    detail: str = ""


@dataclass(frozen=True)
class EstimatorWork:
    """The onboard estimator's work in a streaming phase, from the sensor's status: exposures it took and
    estimator updates it made."""

    exposures: int
    updates: int


@dataclass(frozen=True)
class StreamCount:
    """Where a streaming phase's frames went, from the host's stream loop and the sensor's status read before and
    after the phase.

    ``expected``: frames the phase asks for; ``received``: frames the host got; ``lost_on_link``: frames missing
    up to the last received one, counted from the stream's start (``link.stats``); ``exposures``: frames the sensor
    took from its source in the phase; ``held_at_start``: frames its source still held when the phase began (None:
    unknown); ``ended_early``: the sensor reported the end of its source (END_OF_STREAM) before ``expected`` frames
    arrived."""

    expected: int
    received: int
    lost_on_link: int
    exposures: int
    held_at_start: int | None = None
    ended_early: bool = False

    @property
    def in_flight_at_stop(self) -> int:
        """Frames the sensor sent but the host neither received nor saw missing: on their way (line, adapter, the
        host's buffers) when the host stopped the stream; a restarted stream drops them (``Link.set_streaming``)."""
        return max(self.exposures - self.received - self.lost_on_link, 0)

    @property
    def complete(self) -> bool:
        """The rule: a phase is complete when the host received every frame it asked for (the stream loop goes on
        past frames lost on the link, so it falls short only when the sensor's source ends first)."""
        return self.received >= self.expected

    def as_dict(self) -> dict:
        return {
            "frames_expected": self.expected,
            "frames_received": self.received,
            "frames_lost_on_link": self.lost_on_link,
            "frames_in_flight_at_stop": self.in_flight_at_stop,
            "sensor_exposures": self.exposures,
            "sensor_frames_held_at_start": self.held_at_start,
            "stream_ended_early": self.ended_early,
            "complete": self.complete,
        }


def incomplete_reason(drift: StreamCount, calibration: StreamCount | None, spare_frames: int) -> str | None:
    """Why the drift phase fell short of its frames, from the counts (None when it did not): the sensor's replay holds
    the two phases and ``spare_frames`` more; what the calibration phase consumed beyond its frames (in flight when
    its stream stopped, or lost on the link) and the drift phase's own losses come out of the spare."""
    if drift.complete:
        return None
    text = f"the sensor sent {drift.received} of the {drift.expected} drift frames"
    if drift.ended_early:
        used = []
        if calibration is not None:
            used.append(f"{calibration.in_flight_at_stop} in flight when the calibration stream stopped")
            if calibration.lost_on_link:
                used.append(f"{calibration.lost_on_link} lost on the link while calibrating")
        if drift.lost_on_link:
            used.append(f"{drift.lost_on_link} lost on the link in the drift phase")
        detail = f": {', '.join(used)}" if used else ""
        text += (
            f" before its replay ran out ({spare_frames} spare frames; the sensor took frames the host never got"
            f"{detail}; a host that reads slower than the link delivers falls behind)"
        )
    return text


@dataclass
class BenchRun:
    """Everything a bench run produced, as the report needs it.

    ``cal_estimates`` / ``drift_estimates``: (frame counter of the estimate's last update, ``Estimate``) read in each
    streaming phase; ``cal_sim`` / ``drift_sim``: the simulator's results (session and truth) of the two phases;
    ``data`` and ``ref_info``: the calibration data built from the streamed session and where its reference
    directions came from; ``outcome``: the host calibration; ``uploaded`` / ``active``: the safe upload's result and
    the set read back afterwards; ``cal_stream`` / ``drift_stream``: where each streaming phase's frames went;
    ``spare_frames``: frames the sensor's replay holds beyond each phase, ``replay_frames`` all its frames;
    ``drift_first_counter``: the frame counter of the first frame the drift stream delivered."""

    cfg: BenchConfig
    nominal: CameraParams
    cal_sim: SimResult
    drift_sim: SimResult
    data: CalibrationData | None = None
    ref_info: SessionReferences | None = None
    outcome: CalibrationOutcome | None = None
    uploaded: UploadResult | None = None
    active: ActiveParams | None = None
    upload_steps: list[str] = field(default_factory=list)
    cal_estimates: list[tuple[int, Estimate]] = field(default_factory=list)
    drift_estimates: list[tuple[int, Estimate]] = field(default_factory=list)
    cal_stream: StreamCount | None = None
    drift_stream: StreamCount = StreamCount(0, 0, 0, 0)
    drift_work: EstimatorWork = EstimatorWork(0, 0)
    spare_frames: int = 0
    replay_frames: int | None = None
    drift_first_counter: int | None = None
    phases: list[Phase] = field(default_factory=list)


# ------------------------------------------------------------------------------------------ per-quantity figures
def rms(a: np.ndarray) -> float:
    """Root mean square of ``a`` (NaN for no values)."""
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def truth_focal_mm(sim: SimResult) -> np.ndarray:
    """The simulator's true focal length [mm] at each frame."""
    return np.asarray(sim.truth["focal_length_mm"], dtype=np.float64)


def truth_attitudes(sim: SimResult) -> np.ndarray:
    """The simulator's true attitude matrices (n_frames, 3, 3)."""
    return np.asarray(sim.truth["attitude"], dtype=np.float64).reshape(-1, 3, 3)


def estimate_rows(estimates: list[tuple[int, Estimate]]) -> dict[str, np.ndarray]:
    """Polled estimates as columns (frame, f_mm, x0_px, y0_px and their 1-sigma, n_updates, base generation)."""
    if not estimates:  # same keys and dtypes as below (integer columns index arrays)
        empty = {k: np.zeros(0) for k in ("f_mm", "x0_px", "y0_px", "sigma_f_mm", "sigma_x0_px", "sigma_y0_px")}
        return empty | {k: np.zeros(0, dtype=np.int64) for k in ("frame", "n_updates", "generation")}
    vals = np.array([e.values for _, e in estimates], dtype=np.float64)
    sig = np.array([e.sigma for _, e in estimates], dtype=np.float64)
    return {
        "frame": np.array([f for f, _ in estimates], dtype=np.int64),
        "f_mm": vals[:, 0],
        "x0_px": vals[:, 1],
        "y0_px": vals[:, 2],
        "sigma_f_mm": sig[:, 0],
        "sigma_x0_px": sig[:, 1],
        "sigma_y0_px": sig[:, 2],
        "n_updates": np.array([e.n_updates for _, e in estimates], dtype=np.int64),
        "generation": np.array([e.base_generation for _, e in estimates], dtype=np.int64),
    }


def attitude_error_vectors_arcsec(data, theta: np.ndarray, truth_c: np.ndarray, frame_index: np.ndarray) -> np.ndarray:
    """Per-frame attitude from the camera ``theta`` (the least-squares attitude over the frame's stars) against the
    simulator's truth, as the small rotation vector phi [arcsec] of the error rotation C_est C_true^T = I - [phi x]
    in the sensor frame: phi_x, phi_y tilt the boresight, phi_z is the roll about it."""
    est = fitted_attitudes(data, theta)
    d = np.einsum("fij,fkj->fik", est, truth_c[frame_index])
    phi = 0.5 * np.stack([d[:, 1, 2] - d[:, 2, 1], d[:, 2, 0] - d[:, 0, 2], d[:, 0, 1] - d[:, 1, 0]], axis=1)
    return phi * ARCSEC_PER_RAD


def attitude_error_summary(phi_arcsec: np.ndarray) -> dict:
    """Boresight (tilt) and roll errors: RMS in all, the constant part (a principal-point or focal error acts as a
    fixed misalignment, which a ground alignment absorbs), and the frame-to-frame scatter around it."""
    bias = np.mean(phi_arcsec, axis=0)
    scatter = phi_arcsec - bias
    return {
        "boresight_rms": rms(np.hypot(phi_arcsec[:, 0], phi_arcsec[:, 1])),
        "roll_rms": rms(phi_arcsec[:, 2]),
        "boresight_bias": float(np.hypot(bias[0], bias[1])),
        "roll_bias": float(bias[2]),
        "boresight_scatter_rms": rms(np.hypot(scatter[:, 0], scatter[:, 1])),
        "roll_scatter_rms": rms(scatter[:, 2]),
    }


def drift_frame_index(cfg: BenchConfig, drift_sim: SimResult, frames: np.ndarray) -> np.ndarray:
    """Index into the drift phase's truth of each sensor frame counter (the drift phase begins at frame
    :func:`~hostlink.mission.config.drift_first_frame` of the sensor's replay)."""
    return frames - drift_first_frame(cfg) - int(drift_sim.session.frame[0])


def within_drift_phase(cfg: BenchConfig, drift_index: np.ndarray) -> np.ndarray:
    """Which estimates (by drift-phase index, in reading order) the tracking figure scores: those of the phase's own
    ``cfg.drift_frames`` exposures, and the first one read past them (the phase's last state; the sensor takes
    exposures until the host's stop reaches it). The later reads come from exposures still in flight, past the phase,
    and how many there are depends on the host's timing."""
    drift_index = np.asarray(drift_index, dtype=np.int64)
    keep = drift_index < cfg.drift_frames
    past = np.flatnonzero(~keep)
    if past.size:
        keep[past[0]] = True
    return keep


def replay_truth_attitudes(
    cfg: BenchConfig, cal_sim: SimResult, drift_sim: SimResult, frames: np.ndarray
) -> np.ndarray:
    """The true attitude (n, 3, 3) of each sensor frame counter in ``frames``: the calibration phase's frames, then
    the drift phase's from :func:`~hostlink.mission.config.drift_first_frame` on (a calibration stream that lost
    frames on the link goes on into the calibration phase's spare frames)."""
    frames = np.asarray(frames, dtype=np.int64)
    in_cal = frames < drift_first_frame(cfg)
    out = np.empty((frames.size, 3, 3))
    out[in_cal] = truth_attitudes(cal_sim)[frames[in_cal] - int(cal_sim.session.frame[0])]
    out[~in_cal] = truth_attitudes(drift_sim)[drift_frame_index(cfg, drift_sim, frames[~in_cal])]
    return out


# ------------------------------------------------------------------------------------------------- the summary
def summarise(run: BenchRun) -> dict:
    """The run's summary (the content of ``summary.json``, docs/commands.md ``bench``)."""
    from hostlink.links.operations import float32_equal
    from onboard.prior import sigma_from_dict

    cfg, nominal, outcome, data = run.cfg, run.nominal, run.outcome, run.data
    # attitude against truth, for the frames the calibration used
    truth_c = replay_truth_attitudes(cfg, run.cal_sim, run.drift_sim, data.frame_number)
    frame_index = np.arange(truth_c.shape[0])
    att_before = attitude_error_summary(
        attitude_error_vectors_arcsec(data, nominal.model_vector(), truth_c, frame_index)
    )
    att_after = attitude_error_summary(
        attitude_error_vectors_arcsec(data, outcome.params.model_vector(), truth_c, frame_index)
    )

    n_dof = len(outcome.estimate) + 3 * data.n_frames
    floor_px = float(np.sqrt(2.0) * cfg.noise_px * np.sqrt(max(1.0 - n_dof / (2.0 * data.n_obs), 0.0)))
    truth = cfg.camera
    active, uploaded = run.active, run.uploaded
    return {
        "config": {k: v for k, v in asdict(cfg).items() if k not in ("camera", "nominal", "site", "weather")}
        | {"site": asdict(cfg.site) if cfg.site else None, "weather": asdict(cfg.weather) if cfg.weather else None},
        "transport": cfg.transport,
        "precision": cfg.precision,
        "firmware": cfg.firmware,
        "reference_directions": run.ref_info.source,
        "refraction": run.ref_info.refraction,
        "residual_before": outcome.before,
        "residual_after": outcome.after,
        "noise_floor_rms_px": floor_px,
        "interstar_rms_rad": {"before": outcome.interstar_before_rad, "after": outcome.interstar_after_rad},
        "rejected": outcome.rejected,
        "attitude_error_arcsec": {"before": att_before, "after": att_after},
        "parameters": {
            "true": {"focal_length_mm": truth.focal_length_mm, "principal_point_px": list(truth.principal_point_px)},
            "nominal": {
                "focal_length_mm": nominal.focal_length_mm,
                "principal_point_px": list(nominal.principal_point_px),
            },
            "calibrated": {
                "focal_length_mm": outcome.params.focal_length_mm,
                "principal_point_px": list(outcome.params.principal_point_px),
            },
            "sigma": outcome.sigma(),
            "error_focal_um": (outcome.params.focal_length_mm - truth.focal_length_mm) * 1000.0,
            "error_principal_point_px": [
                outcome.params.principal_point_px[i] - truth.principal_point_px[i] for i in range(2)
            ],
        },
        "upload": {
            "generation": uploaded.generation,
            "crc32": f"0x{uploaded.crc32:08x}",
            "read_back_equal_float32": bool(
                float32_equal(active.params, outcome.params, active.sigma, sigma_from_dict(outcome.sigma()))
            ),
            "sigma_prior_parameters": int(np.count_nonzero(np.isfinite(active.sigma) & (active.sigma > 0))),
            "steps": run.upload_steps,
        },
        "success": run.drift_stream.complete,
        "link": {
            "lost_messages": int(run.drift_stream.lost_on_link + (run.cal_stream.lost_on_link if run.cal_stream else 0))
        },
        "calibration_stream": run.cal_stream.as_dict() if run.cal_stream else None,
        "drift_tracking": drift_tracking_summary(run),
        "after_upload": after_upload_summary(cfg, run.drift_sim, run.drift_estimates),
        "phases": [asdict(p) for p in run.phases],
    }


def drift_tracking_summary(run: BenchRun) -> dict:
    """The drift phase's focal tracking (``summary.json``'s ``drift_tracking``): the onboard estimates read within the
    phase (:func:`within_drift_phase`) against the simulator's true focal length, RMS over all of them and once
    converged, beside the estimator's own 1-sigma and what the stream delivered."""
    cfg = run.cfg
    est = estimate_rows(run.drift_estimates)
    f_true = truth_focal_mm(run.drift_sim)
    drift_index = drift_frame_index(cfg, run.drift_sim, est["frame"])
    valid = (drift_index >= 0) & (drift_index < f_true.size) & (est["n_updates"] > 0)
    valid &= within_drift_phase(cfg, drift_index)
    err_um = (est["f_mm"][valid] - f_true[drift_index[valid]]) * 1000.0
    # "once converged": after the first third of the drift phase (the filter restarted at the upload and its drift
    # detector needs a few hundred frames to switch the focal random walk on)
    settled = drift_index[valid] >= cfg.drift_frames // 3
    return {
        "amplitude_um": drift_amplitude_um(cfg),
        "period_frames": cfg.drift_period_frames,
        "frames_streamed": run.drift_stream.received,
        "first_frame_drift_index": None
        if run.drift_first_counter is None
        else int(drift_frame_index(cfg, run.drift_sim, np.array([run.drift_first_counter]))[0]),
        **run.drift_stream.as_dict(),
        "incomplete_because": incomplete_reason(run.drift_stream, run.cal_stream, run.spare_frames),
        "estimates_read": int(est["frame"].size),
        "estimator_updates": run.drift_work.updates,
        "focal_error_rms_um_converged": rms(err_um[settled]) if np.any(settled) else None,
        "focal_error_rms_um_all": rms(err_um) if err_um.size else None,
        # the estimator's own 1-sigma over the same estimates: the scatter its error should show if it is honest
        "focal_sigma_rms_um_converged": rms(est["sigma_f_mm"][valid][settled] * 1000.0) if np.any(settled) else None,
        "not_tracked_because": None if np.any(settled) else tracking_gap_reason(cfg, est["frame"].size, run.drift_work),
        "focal_true_rms_deviation_um": rms((f_true[: cfg.drift_frames] - np.mean(f_true[: cfg.drift_frames])) * 1e3),
    }


def tracking_gap_reason(cfg: BenchConfig, n_estimates: int, work: EstimatorWork) -> str:
    """Why the drift phase yields no tracking figure, from what the run shows (never a guess)."""
    if work.updates == 0:
        return f"the onboard estimator made no update in the drift phase ({work.exposures} exposures taken)"
    if n_estimates == 0:
        return "no onboard estimate could be read during the drift phase"
    return (
        f"the estimator's last update came before frame {cfg.drift_frames // 3} of the drift phase, where tracking "
        "is scored"
    )


def after_upload_summary(cfg: BenchConfig, drift_sim: SimResult, drift_estimates: list[tuple[int, Estimate]]) -> dict:
    """How the onboard estimator restarted from the uploaded set: error and 1-sigma of f [um], x0, y0 [px] at the
    first estimate read after the upload and at the last one (the drift phase's end), and the RMS error of x0, y0 (and
    the largest |error|) over the drift phase."""
    est = estimate_rows(drift_estimates)
    if est["frame"].size == 0:
        return {}
    f_true = truth_focal_mm(drift_sim)
    drift_index = np.clip(drift_frame_index(cfg, drift_sim, est["frame"]), 0, f_true.size - 1)
    err = {
        "f_um": (est["f_mm"] - f_true[drift_index]) * 1000.0,
        "x0_px": est["x0_px"] - cfg.camera.principal_point_px[0],
        "y0_px": est["y0_px"] - cfg.camera.principal_point_px[1],
    }
    sig = {"f_um": est["sigma_f_mm"] * 1000.0, "x0_px": est["sigma_x0_px"], "y0_px": est["sigma_y0_px"]}
    return {
        "first_estimate": {"n_updates": int(est["n_updates"][0])}
        | {f"error_{k}": float(v[0]) for k, v in err.items()}
        | {f"sigma_{k}": float(v[0]) for k, v in sig.items()},
        "last_estimate": {"n_updates": int(est["n_updates"][-1])}
        | {f"error_{k}": float(v[-1]) for k, v in err.items()}
        | {f"sigma_{k}": float(v[-1]) for k, v in sig.items()},
        "x0_error_rms_px": rms(err["x0_px"]),
        "y0_error_rms_px": rms(err["y0_px"]),
        "x0_error_max_px": float(np.max(np.abs(err["x0_px"]))),
        "y0_error_max_px": float(np.max(np.abs(err["y0_px"]))),
        "principal_point_normalised_error_rms": rms(
            np.concatenate([err["x0_px"] / sig["x0_px"], err["y0_px"] / sig["y0_px"]])
        ),
    }


# ------------------------------------------------------------------------------------------------- as text
def nan_to_null(o):
    """The summary with every non-finite float as None (JSON has no NaN: strict readers refuse it)."""
    if isinstance(o, dict):
        return {k: nan_to_null(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [nan_to_null(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


def json_default(o):
    """JSON for what the summary holds beside plain Python values: numpy scalars and arrays, paths."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def tracking_text(summary: dict) -> str:
    """The drift-tracking figure as one phrase: the error once converged, or why there is none."""
    track = summary["drift_tracking"]
    if track["focal_error_rms_um_converged"] is None:
        return f"not scored: {track['not_tracked_because']}"
    text = f"tracking error {track['focal_error_rms_um_converged']:.2f} um RMS once converged"
    sigma = track.get("focal_sigma_rms_um_converged")
    return text if sigma is None else f"{text} (onboard 1-sigma {sigma:.2f})"


def summary_table(summary: dict) -> list[tuple[str, str, str]]:
    """(quantity, before, after) rows for the terminal."""
    b, a = summary["residual_before"], summary["residual_after"]
    att_b, att_a = summary["attitude_error_arcsec"]["before"], summary["attitude_error_arcsec"]["after"]
    p = summary["parameters"]
    sig = p["sigma"]
    track = summary["drift_tracking"]
    pp_nominal = [p["nominal"]["principal_point_px"][i] - p["true"]["principal_point_px"][i] for i in range(2)]
    return [
        (
            "residual RMS (px)",
            f"{b['rms_px']:.4f}",
            f"{a['rms_px']:.4f} (noise floor {summary['noise_floor_rms_px']:.4f})",
        ),
        ("residual max (px)", f"{b['max_px']:.3f}", f"{a['max_px']:.3f}"),
        ("residual RMS (arcsec)", f"{b['rms_arcsec']:.3f}", f"{a['rms_arcsec']:.3f}"),
        (
            "attitude scatter, boresight / roll (arcsec RMS)",
            f"{att_b['boresight_scatter_rms']:.2f} / {att_b['roll_scatter_rms']:.2f}",
            f"{att_a['boresight_scatter_rms']:.3f} / {att_a['roll_scatter_rms']:.3f}",
        ),
        (
            "attitude bias, boresight / roll (arcsec)",
            f"{att_b['boresight_bias']:.1f} / {att_b['roll_bias']:.1f}",
            f"{att_a['boresight_bias']:.1f} / {att_a['roll_bias']:.1f} (= principal point error x 1/F)",
        ),
        (
            "focal length error (um)",
            f"{(p['nominal']['focal_length_mm'] - p['true']['focal_length_mm']) * 1000:.1f}",
            f"{p['error_focal_um']:.2f} (1-sigma {sig['focal_length_mm'] * 1000:.2f})",
        ),
        (
            "principal point error (px)",
            "{:.2f}, {:.2f}".format(*pp_nominal),
            "{:.2f}, {:.2f} (1-sigma {:.2f}, {:.2f})".format(
                *p["error_principal_point_px"], *sig["principal_point_px"]
            ),
        ),
        (
            "focal drift tracking (um RMS)",
            f"{track['focal_true_rms_deviation_um']:.2f} (the drift itself)",
            tracking_text(summary),
        ),
        (
            "drift frames received",
            "",
            f"{track['frames_received']} of {track['frames_expected']} ({track['frames_lost_on_link']} lost on the "
            f"link){'' if track['complete'] else ': INCOMPLETE'}",
        ),
        (
            "onboard estimator updates, drift phase",
            "",
            f"{track['estimator_updates']} of {track['sensor_exposures']} exposures "
            f"({100.0 * track['estimator_updates'] / max(track['sensor_exposures'], 1):.0f} %)",
        ),
    ]
