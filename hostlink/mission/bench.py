"""The main job, ``hostlink bench``: the whole mission end to end against an emulated sensor (issue 7).

1. The sky simulator makes a session through a *true* camera that differs from the sensor's nominal one, as after
   launch: a calibration phase (static camera) then a drift phase (sinusoidal thermal focal-length drift).
2. An emulated sensor (``hostlink emulate``, a separate process running the onboard firmware) replays it over a real
   link (a serial pty by default); the host streams the calibration phase with a progress bar.
3. The host calibrates the streamed session (reference directions from Hipparcos at each frame's time, as for any
   recorded session; refraction added for a ground site).
4. The parameters are uploaded with the six-step safe upload and verified by read-back.
5. The host streams the drift phase while polling the onboard recursive estimate, which restarted from the uploaded
   set and follows the drift.
6. The report: residuals before/after (px and arcsec), attitude error against the simulator's truth, focal-length
   tracking; ``summary.json`` and PNG plots in the output folder, a short table on the terminal.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import LinkError, UserError
from hostlink.files.params import load_params, save_params
from onboard.params import CameraParams, Distortion
from onboard.site import Site, Weather

ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi

#: The embedded default "true" camera: seed 004's camera (Table 1) after a launch shock: the principal point and
#: focal length moved, and small decentering and thin-prism terms appeared beside the radial distortion. Every term
#: is a few tenths of a pixel at the corner, the regime where calibration matters at the 0.05 px noise level.
BENCH_TRUE_CAMERA = CameraParams(
    focal_length_mm=70.2262,
    pixel_pitch_um=12.0,
    principal_point_px=(500.0, 530.0),
    image_size_px=(1024, 1024),
    distortion=Distortion(k1=-2.0e-10, k2=3.5e-15, p1=3.0e-7, p2=-2.0e-7, s1=1.5e-7, s2=-1.0e-7),
)


@dataclass
class BenchConfig:
    out_dir: Path = Path("bench-report")
    transport: str = "serial"
    cal_frames: int = 600
    drift_frames: int = 3000
    #: exposures the sensor's replay holds beyond the two phases: a sensor keeps taking exposures until the host's
    #: "stop streaming" reaches it, so the frames in flight then (a few on serial, up to ~100 in a CAN hub's queues)
    #: are consumed between the phases; the spare frames keep the drift phase at its full length
    spare_frames: int = 256
    noise_px: float = 0.05
    misid_fraction: float = 0.0
    drift_um: float = 6.0
    drift_period_frames: float = 3000.0
    seed: int = 1
    camera: CameraParams = field(default_factory=lambda: BENCH_TRUE_CAMERA)
    nominal: CameraParams | None = None  # default: hostlink/data/seed004_nominal.json
    site: Site | None = None
    weather: Weather | None = None
    maglim: float = 6.0  # faintest Hipparcos magnitude simulated (SimConfig.maglim)
    min_stars: int = 10  # fewest stars per frame (SimConfig.min_stars)
    max_stars: int = 30  # most stars per frame, brightest kept (SimConfig.max_stars)
    poll_every_frames: int = 25
    emulator_args: tuple[str, ...] = ()
    t0_iso: str = "2026-03-14T02:10:00.000Z"


@dataclass
class Phase:
    name: str
    seconds: float
    detail: str = ""


# ------------------------------------------------------------------------------------------------ the steps
def simulate_phases(cfg: BenchConfig):
    """Calibration phase (static camera) + drift phase (sinusoidal focal drift), one continuous session."""
    from hostlink.files.times import iso_plus_seconds
    from hostlink.sky.simulate import SimConfig, simulate

    common = dict(
        camera=cfg.camera,
        noise_px=cfg.noise_px,
        misid_fraction=cfg.misid_fraction,
        site=cfg.site,
        weather=cfg.weather,
        frame_interval_s=1.0,
        maglim=cfg.maglim,
        min_stars=cfg.min_stars,
        max_stars=cfg.max_stars,
    )
    cal = simulate(SimConfig(frames=cfg.cal_frames, seed=cfg.seed, t0_iso=cfg.t0_iso, **common))
    drift = simulate(
        SimConfig(
            frames=cfg.drift_frames + cfg.spare_frames,
            seed=cfg.seed + 1000,
            t0_iso=iso_plus_seconds(cfg.t0_iso, float(cfg.cal_frames)),
            focal_drift_um=cfg.drift_um,
            focal_drift_period_frames=cfg.drift_period_frames,
            **common,
        )
    )
    return cal, drift


def concatenate_sessions(first, second, frame_offset: int):
    """One session: ``second``'s frame numbers shifted by ``frame_offset`` and appended to ``first``."""
    from hostlink.files.session import Session

    def cat(a, b):
        return None if a is None or b is None else np.concatenate([a, b])

    return Session(
        frame=np.concatenate([first.frame, second.frame + frame_offset]),
        t_utc=np.concatenate([first.t_utc, second.t_utc]),
        star_id=np.concatenate([first.star_id, second.star_id]),
        x_px=np.concatenate([first.x_px, second.x_px]),
        y_px=np.concatenate([first.y_px, second.y_px]),
        mag=cat(first.mag, second.mag),
        ra_deg=cat(first.ra_deg, second.ra_deg),
        dec_deg=cat(first.dec_deg, second.dec_deg),
    )


def sensor_reference_session(session, site: Site | None, weather: Weather | None):
    """The replay file the emulated sensor holds: a ground sensor turns its catalogue directions into observed ones
    itself (diurnal aberration, then refraction: seed 001 sec. 4, ``onboard.refraction.topocentric_observed``), so
    its recursive estimator sees corrected references."""
    if site is None:
        return session
    from hostlink.sky.references import session_references, session_with_references

    return session_with_references(session, session_references(session, site, weather))


class Emulator:
    """``hostlink emulate`` as a child process; ``link`` is the string from its first stdout line."""

    def __init__(self, transport: str, args: list[str], startup_timeout_s: float = 120.0) -> None:
        import selectors

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "hostlink.cli", "emulate", "--transport", transport, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        line = self.proc.stdout.readline() if sel.select(startup_timeout_s) else ""
        if not line:
            self.stop()
            err = (self.proc.stderr.read() or "").strip().splitlines()
            raise UserError(f"the emulated sensor did not start: {err[-1] if err else 'no output'}")
        try:
            self.info = json.loads(line)
            self.link = str(self.info["link"])
        except (ValueError, KeyError):
            self.stop()
            raise UserError(f"the emulated sensor printed an unexpected first line: {line.strip()!r}") from None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def stream_phase(link, n_frames: int, poll_every: int, progress: Callable[[int], None]):
    """Stream ``n_frames`` frames through the one stream loop (``hostlink.links.operations.stream_frames``), reading
    the onboard estimate every ``poll_every`` frames and once more at the end of the phase.

    Returns (frames, estimates, estimator) where estimates are (frame counter of the estimate's last update, Estimate)
    and ``estimator`` counts the phase's work: exposures the sensor took and estimator updates (from its status)."""
    from hostlink.links.operations import poll_estimate, stream_frames

    before = link.status()
    result = stream_frames(link, n_frames, progress=progress, poll_every_frames=poll_every)
    final = poll_estimate(link, result.frames_received)
    after = link.status()
    polls = [*result.polls, final]
    # key each estimate by the last frame the sensor's estimator processed (it can run ahead of what the host has
    # received while frames wait in the line's buffers)
    estimates = [(int(p.estimate.last_frame), p.estimate) for p in polls if p.estimate is not None]
    exposures = int(after.frames_processed - before.frames_processed)
    same_estimator = after.active_generation == before.active_generation  # no commit restarted it meanwhile
    updates = int(after.estimator_updates - (before.estimator_updates if same_estimator else 0))
    return result.frames, estimates, {"exposures": exposures, "updates": updates}


def estimate_rows(estimates) -> dict[str, np.ndarray]:
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
    """Per-frame attitude from the camera ``theta`` (SVD over the frame's stars) against the simulator's truth, as
    the small rotation vector phi [arcsec] of the error rotation C_est C_true^T = I - [phi x] in the sensor frame:
    phi_x, phi_y tilt the boresight, phi_z is the roll about it."""
    from hostlink.calibration.report import fitted_attitudes

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


def rms(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


# ------------------------------------------------------------------------------------------------- the run
def run_bench(cfg: BenchConfig, say: Callable[[str], None] = print, show_progress: bool = True) -> dict:
    """Run the whole bench; returns the summary (also written to ``out_dir/summary.json``)."""
    from hostlink.calibration.data import calibration_data_from_session
    from hostlink.calibration.run import calibrate
    from hostlink.files.session import write_session
    from hostlink.links import open_link
    from hostlink.links.operations import frames_to_session, read_active_params, safe_upload
    from hostlink.progress import progress_bar
    from hostlink.sky.simulate import data_file
    from onboard.prior import sigma_from_dict

    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    nominal = cfg.nominal or load_params(data_file("seed004_nominal.json"))
    phases: list[Phase] = []
    t_start = time.perf_counter()

    # 1. truth
    t = time.perf_counter()
    cal_sim, drift_sim = simulate_phases(cfg)
    replay = concatenate_sessions(cal_sim.session, drift_sim.session, cfg.cal_frames)
    replay_path = out / "sensor-replay.csv"
    write_session(replay_path, sensor_reference_session(replay, cfg.site, cfg.weather))
    save_params(out / "true-camera.json", cfg.camera)
    nominal_path = out / "nominal.json"
    save_params(nominal_path, nominal)
    phases.append(
        Phase("simulate", time.perf_counter() - t, f"{cfg.cal_frames} + {cfg.drift_frames} frames, {len(replay)} stars")
    )
    say(f"[1/6] simulated {cfg.cal_frames} calibration + {cfg.drift_frames} drift frames ({len(replay)} stars)")

    # 2. stream the calibration phase from the emulated sensor
    t = time.perf_counter()
    args = [
        "--replay",
        str(replay_path),
        "--nominal",
        str(nominal_path),
        "--noise-px",
        repr(cfg.noise_px),
        *cfg.emulator_args,
    ]
    with Emulator(cfg.transport, args) as emu:
        say(f"[2/6] emulated sensor on {emu.link}")
        with open_link(emu.link) as link:
            before_active = read_active_params(link)
            with progress_bar("streaming calibration frames", cfg.cal_frames, show_progress) as advance:
                cal_frames, cal_estimates, _ = stream_phase(link, cfg.cal_frames, cfg.poll_every_frames, advance)
            lost_cal = link.stats.lost_messages
            if len(cal_frames) < cfg.cal_frames:
                raise LinkError(f"the sensor sent {len(cal_frames)} of {cfg.cal_frames} calibration frames")
            streamed = frames_to_session(cal_frames)
            write_session(out / "session.csv", streamed)
            phases.append(
                Phase(
                    "stream",
                    time.perf_counter() - t,
                    f"{len(cal_frames)} frames, {len(streamed)} stars, {lost_cal} lost",
                )
            )
            say(f"      streamed {len(cal_frames)} frames / {len(streamed)} stars, {lost_cal} messages lost")

            # 3. calibrate on the host
            t = time.perf_counter()
            data, ref_info = calibration_data_from_session(streamed, cfg.site, cfg.weather)
            try:
                outcome = calibrate(data, nominal, "bundle", noise_px=None)
            except ValueError as exc:  # what the streamed data cannot support (e.g. a nominal far from the camera)
                raise UserError(f"calibration failed: {exc}") from None
            from hostlink.calibration.run import result_extras

            save_params(out / "calibrated.json", outcome.params, result_extras(outcome))
            phases.append(Phase("calibrate", time.perf_counter() - t, f"bundle, {len(outcome.history)} iterations"))
            say(f"[3/6] calibrated: residual {outcome.before['rms_px']:.3f} -> {outcome.after['rms_px']:.4f} px RMS")

            # 4. safe upload, verified by read-back
            t = time.perf_counter()
            steps: list[str] = []
            # the calibration's 1-sigma travels with the set: the onboard estimator restarts from it as its prior
            uploaded = safe_upload(
                link,
                outcome.params,
                step=lambda k, text: steps.append(f"{k}. {text}"),
                sigma=sigma_from_dict(outcome.sigma()),
            )
            active = read_active_params(link)
            phases.append(Phase("upload", time.perf_counter() - t, f"generation {uploaded.generation}"))
            say(f"[4/6] uploaded and verified: generation {before_active.generation} -> {uploaded.generation}")

            # 5. the onboard estimator runs on through the drift phase
            t = time.perf_counter()
            with progress_bar("streaming drift frames", cfg.drift_frames, show_progress) as advance:
                drift_frames, drift_estimates, estimator_work = stream_phase(
                    link, cfg.drift_frames, cfg.poll_every_frames, advance
                )
            phases.append(Phase("track", time.perf_counter() - t, f"{len(drift_frames)} frames"))
            say(
                f"[5/6] {len(drift_frames)} drift frames streamed; the onboard estimator updated on "
                f"{estimator_work['updates']} of the {estimator_work['exposures']} exposures the sensor took "
                f"({len(drift_estimates)} estimates read)"
            )
            lost_total = link.stats.lost_messages

    # 6. report
    summary = summarise(
        cfg,
        nominal,
        outcome,
        data,
        ref_info,
        cal_sim,
        drift_sim,
        active,
        uploaded,
        lost_total,
        cal_estimates,
        drift_estimates,
        len(drift_frames),
        estimator_work,
        steps,
        phases,
    )
    summary["elapsed_s"] = time.perf_counter() - t_start
    write_plots(out, cfg, nominal, outcome, data, cal_sim, drift_sim, cal_estimates, drift_estimates, summary)
    (out / "summary.json").write_text(
        json.dumps(_nan_to_null(summary), indent=2, default=_json_default, allow_nan=False) + "\n"
    )
    return summary


def _nan_to_null(o):
    """The summary with every non-finite float as None (JSON has no NaN: strict readers refuse it)."""
    if isinstance(o, dict):
        return {k: _nan_to_null(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_nan_to_null(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def truth_focal_mm(sim) -> np.ndarray:
    return np.asarray(sim.truth["focal_length_mm"], dtype=np.float64)


def truth_attitudes(sim) -> np.ndarray:
    return np.asarray(sim.truth["attitude"], dtype=np.float64).reshape(-1, 3, 3)


def summarise(
    cfg,
    nominal,
    outcome,
    data,
    ref_info,
    cal_sim,
    drift_sim,
    active,
    uploaded,
    lost_total,
    cal_estimates,
    drift_estimates,
    n_drift_streamed,
    estimator_work,
    steps,
    phases,
) -> dict:
    from hostlink.links.operations import float32_equal
    from onboard.prior import sigma_from_dict

    # attitude against truth, for the frames the calibration used
    first_frame = int(cal_sim.session.frame[0])
    frame_index = data.frame_number - first_frame
    truth_c = truth_attitudes(cal_sim)
    att_before = attitude_error_summary(
        attitude_error_vectors_arcsec(data, nominal.model_vector(), truth_c, frame_index)
    )
    att_after = attitude_error_summary(
        attitude_error_vectors_arcsec(data, outcome.params.model_vector(), truth_c, frame_index)
    )

    # focal tracking in the drift phase
    est = estimate_rows(drift_estimates)
    f_true = truth_focal_mm(drift_sim)
    drift_index = est["frame"] - cfg.cal_frames - int(drift_sim.session.frame[0])
    valid = (drift_index >= 0) & (drift_index < f_true.size) & (est["n_updates"] > 0)
    err_um = (est["f_mm"][valid] - f_true[drift_index[valid]]) * 1000.0
    # "once converged": after the first third of the drift phase (the filter restarted at the upload and its drift
    # detector needs a few hundred frames to switch the focal random walk on)
    settled = drift_index[valid] >= cfg.drift_frames // 3
    n_dof = len(outcome.estimate) + 3 * data.n_frames
    floor_px = float(np.sqrt(2.0) * cfg.noise_px * np.sqrt(max(1.0 - n_dof / (2.0 * data.n_obs), 0.0)))
    truth = cfg.camera
    return {
        "config": {k: v for k, v in asdict(cfg).items() if k not in ("camera", "nominal", "site", "weather")}
        | {"site": asdict(cfg.site) if cfg.site else None, "weather": asdict(cfg.weather) if cfg.weather else None},
        "transport": cfg.transport,
        "reference_directions": ref_info.source,
        "refraction": ref_info.refraction,
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
            "steps": steps,
        },
        "link": {"lost_messages": int(lost_total)},
        "drift_tracking": {
            "amplitude_um": cfg.drift_um,
            "period_frames": cfg.drift_period_frames,
            "frames_streamed": n_drift_streamed,
            "estimates_read": int(est["frame"].size),
            "sensor_exposures": estimator_work["exposures"],
            "estimator_updates": estimator_work["updates"],
            "focal_error_rms_um_converged": rms(err_um[settled]) if np.any(settled) else None,
            "focal_error_rms_um_all": rms(err_um) if err_um.size else None,
            "not_tracked_because": None
            if np.any(settled)
            else tracking_gap_reason(cfg, est["frame"].size, estimator_work),
            "focal_true_rms_deviation_um": rms(
                (f_true[: cfg.drift_frames] - np.mean(f_true[: cfg.drift_frames])) * 1e3
            ),
        },
        "after_upload": after_upload_summary(cfg, drift_sim, drift_estimates),
        "phases": [asdict(p) for p in phases],
    }


def tracking_gap_reason(cfg, n_estimates: int, estimator_work: dict) -> str:
    """Why the drift phase yields no tracking figure, from what the run shows (never a guess)."""
    if estimator_work["updates"] == 0:
        return (
            f"the onboard estimator made no update in the drift phase ({estimator_work['exposures']} exposures taken)"
        )
    if n_estimates == 0:
        return "no onboard estimate could be read during the drift phase"
    return (
        f"the estimator's last update came before frame {cfg.drift_frames // 3} of the drift phase, where tracking "
        "is scored"
    )


def after_upload_summary(cfg, drift_sim, drift_estimates) -> dict:
    """How the onboard estimator restarted from the uploaded set: error and 1-sigma of f [um], x0, y0 [px] at the
    first estimate read after the upload, and the RMS error of x0, y0 (and the largest |error|) over the drift phase."""
    est = estimate_rows(drift_estimates)
    if est["frame"].size == 0:
        return {}
    f_true = truth_focal_mm(drift_sim)
    drift_index = np.clip(est["frame"] - cfg.cal_frames - int(drift_sim.session.frame[0]), 0, f_true.size - 1)
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
        "x0_error_rms_px": rms(err["x0_px"]),
        "y0_error_rms_px": rms(err["y0_px"]),
        "x0_error_max_px": float(np.max(np.abs(err["x0_px"]))),
        "y0_error_max_px": float(np.max(np.abs(err["y0_px"]))),
        "principal_point_normalised_error_rms": rms(
            np.concatenate([err["x0_px"] / sig["x0_px"], err["y0_px"] / sig["y0_px"]])
        ),
    }


# ------------------------------------------------------------------------------------------------- plots
def write_plots(
    out: Path, cfg, nominal, outcome, data, cal_sim, drift_sim, cal_estimates, drift_estimates, summary
) -> list[Path]:
    from hostlink.calibration.bundle import residuals
    from hostlink.calibration.plots import _pyplot, residual_field_png
    from hostlink.calibration.report import fitted_attitudes

    paths = []
    theta0 = nominal.model_vector()
    e_before = residuals(data, theta0, fitted_attitudes(data, theta0))
    e_after = residuals(data, outcome.theta, outcome.attitudes)
    for name, e, label in (
        ("residuals-before.png", e_before, "nominal camera"),
        ("residuals-after.png", e_after, "calibrated camera"),
    ):
        path = out / name
        residual_field_png(
            path,
            data.x_px,
            data.y_px,
            e,
            nominal.image_size_px,
            f"Mean residual per cell, {label} (RMS {rms(np.linalg.norm(e, axis=1)):.4f} px)",
        )
        paths.append(path)

    plt = _pyplot()
    cal = estimate_rows(cal_estimates)
    drift = estimate_rows(drift_estimates)
    f_true = np.concatenate([truth_focal_mm(cal_sim), truth_focal_mm(drift_sim)])
    frames_true = np.arange(f_true.size) + int(cal_sim.session.frame[0])

    # estimator convergence: |estimate - truth| of f, x0, y0 against the estimator's own 1-sigma, both phases
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    truth = cfg.camera
    for ax, key, sig, true_val, label_unit, scale in (
        (axes[0], "f_mm", "sigma_f_mm", None, "|f error| [um]", 1000.0),
        (axes[1], "x0_px", "sigma_x0_px", truth.principal_point_px[0], "|x0 error| [px]", 1.0),
        (axes[2], "y0_px", "sigma_y0_px", truth.principal_point_px[1], "|y0 error| [px]", 1.0),
    ):
        for rows, colour, label in (
            (cal, "tab:orange", "cold start from nominal"),
            (drift, "tab:blue", "restarted from the uploaded set"),
        ):
            if rows["frame"].size == 0:
                continue
            ref = np.interp(rows["frame"], frames_true, f_true) if key == "f_mm" else true_val
            ax.semilogy(rows["frame"], np.abs(rows[key] - ref) * scale, color=colour, label=f"|error|, {label}")
            ax.semilogy(rows["frame"], rows[sig] * scale, color=colour, ls=":", label=f"1-sigma, {label}")
        ax.axvline(cfg.cal_frames, color="grey", ls="--", lw=0.8)
        ax.set_ylabel(label_unit)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_title(
        "Onboard recursive estimator: error against truth and its own 1-sigma (dashed: upload)", fontsize=10
    )
    if axes[0].get_legend_handles_labels()[0]:  # nothing to label when the sensor gave no estimate
        axes[0].legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("frame")
    fig.tight_layout()
    path = out / "estimator-convergence.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    paths.append(path)

    # drift tracking
    fig, ax = plt.subplots(figsize=(8, 4.5))
    f_drift_true = truth_focal_mm(drift_sim)
    fr = np.arange(f_drift_true.size) + cfg.cal_frames + int(drift_sim.session.frame[0])
    f_ref = truth.focal_length_mm
    ax.plot(fr, (f_drift_true - f_ref) * 1000.0, color="k", lw=1.2, label="true focal length")
    if drift["frame"].size:
        ax.plot(drift["frame"], (drift["f_mm"] - f_ref) * 1000.0, color="tab:blue", label="onboard estimate")
        ax.fill_between(
            drift["frame"],
            (drift["f_mm"] - drift["sigma_f_mm"] - f_ref) * 1000.0,
            (drift["f_mm"] + drift["sigma_f_mm"] - f_ref) * 1000.0,
            color="tab:blue",
            alpha=0.2,
            label="estimate 1-sigma",
        )
    ax.set_title(f"Thermal focal-length drift: {cfg.drift_um:g} um amplitude; {tracking_text(summary)}", fontsize=10)
    ax.set_xlabel("frame")
    ax.set_ylabel(f"focal length - {f_ref:g} mm [um]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "drift-tracking.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    paths.append(path)
    return paths


def tracking_text(summary: dict) -> str:
    """The drift-tracking figure as one phrase: the error once converged, or why there is none."""
    track = summary["drift_tracking"]
    if track["focal_error_rms_um_converged"] is None:
        return f"not scored: {track['not_tracked_because']}"
    return f"tracking error {track['focal_error_rms_um_converged']:.2f} um RMS once converged"


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
            "onboard estimator updates, drift phase",
            "",
            f"{track['estimator_updates']} of {track['sensor_exposures']} exposures "
            f"({100.0 * track['estimator_updates'] / max(track['sensor_exposures'], 1):.0f} %)",
        ),
    ]
