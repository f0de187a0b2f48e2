"""The main job, ``hostlink bench``: the whole mission end to end against an emulated sensor (issue 7), phase by phase.

1. simulate: the sky simulator makes a session through a *true* camera that differs from the sensor's nominal one,
   as after launch: a calibration phase (static camera) then a drift phase (sinusoidal thermal focal-length drift).
2. stream: an emulated sensor (``hostlink emulate`` in its own process, :class:`EmulatorProcess`) replays it over a
   real link (a serial pty by default); the host streams the calibration phase through the one stream loop.
3. calibrate: the host calibrates the streamed session (reference directions from Hipparcos at each frame's time, as
   for any recorded session; refraction added for a ground site).
4. upload: the parameters go up by the six-step safe upload and are verified by read-back.
5. track: the host streams the drift phase while polling the onboard recursive estimate, which restarted from the
   uploaded set and follows the drift.
6. report: ``summary.json`` and PNG plots in the output folder (:mod:`hostlink.mission.summary`,
   :mod:`hostlink.mission.plots`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hostlink.emulator.process import EmulatorProcess
from hostlink.errors import LinkError, UserError
from hostlink.files.params import save_params
from hostlink.files.session import Session, write_session
from hostlink.mission.config import (
    BenchConfig,
    bench_nominal,
    drift_amplitude_um,
    drift_first_frame,
    spare_frames,
)
from hostlink.mission.summary import BenchRun, EstimatorWork, Phase, StreamCount
from hostlink.progress import progress_bar
from onboard.site import Site, Weather

if TYPE_CHECKING:
    from hostlink.links.base import Link
    from hostlink.sky.simulate import SimResult
    from protocol.messages import CentroidFrame, Estimate


def run_bench(cfg: BenchConfig, say: Callable[[str], None] = print, show_progress: bool = True) -> dict:
    """Run the whole bench; returns the summary (also written to ``out_dir/summary.json``, beside the plots).
    ``say`` gets one line per phase; ``show_progress`` draws a progress bar while frames stream. A drift phase that
    received fewer frames than it asked for (the sensor's replay ran out) is not a success: the report is written
    (``success`` false, the counts and ``incomplete_because``), then a :class:`LinkError` says why."""
    from hostlink.files.atomic import write_json
    from hostlink.links import open_link
    from hostlink.links.operations import read_active_params
    from hostlink.mission.plots import write_plots
    from hostlink.mission.summary import json_default, nan_to_null, summarise
    from onboard.firmware import PRECISIONS

    if cfg.precision not in PRECISIONS:
        raise UserError(f"precision: expected one of {', '.join(PRECISIONS)}, got {cfg.precision!r}")
    if cfg.firmware == "c":  # built (or found in the cache) before anything is simulated or written
        from hostlink.portkit.firmware_c import build_library

        build_library()
    if cfg.precision == "fixed":  # the sensor's nominal in the fixed-point range, before anything is simulated
        from hostlink.calibration.replay import check_fixed_range
        from hostlink.mission.config import bench_nominal

        check_fixed_range(bench_nominal(cfg))
    cfg = replace(cfg, drift_um=drift_amplitude_um(cfg))  # the default scaled to the lens; the report states it
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    run, replay_path, nominal_path = simulate_phase(cfg, out, say)

    t = time.perf_counter()
    args = ["--replay", str(replay_path), "--nominal", str(nominal_path), "--noise-px", repr(cfg.noise_px)]
    args += ["--precision", cfg.precision, "--firmware", cfg.firmware]
    args += ["--phase-start", str(drift_first_frame(cfg))]  # the drift stream begins at the drift phase's first frame
    flash = out / "sensor-flash.img"  # the sensor's NOR-flash banks (--flash); a fresh sensor for every run
    flash.unlink(missing_ok=True)
    with EmulatorProcess(cfg.transport, [*args, *cfg.emulator_args], flash_path=flash) as emulator:
        say(f"[2/6] emulated {cfg.precision} sensor ({cfg.firmware} firmware) on {emulator.link}")
        with open_link(emulator.link, cfg.link_timeout_s) as link:
            generation_before = read_active_params(link).generation
            streamed = stream_calibration_phase(run, link, t, out, say, show_progress)
            calibrate_phase(run, streamed, out, say)
            upload_phase(run, link, generation_before, say)
            track_phase(run, link, say, show_progress)

    summary = summarise(run)
    summary["elapsed_s"] = time.perf_counter() - t_start
    write_plots(out, run, summary)
    write_json(out / "summary.json", nan_to_null(summary), default=json_default)
    say(f"[6/6] report written: {out / 'summary.json'} and PNG plots in {out}")
    if not summary["success"]:  # the figures are written for diagnosis; the run is not a success
        reason = summary["drift_tracking"]["incomplete_because"]
        raise LinkError(f"the drift phase is incomplete: {reason}; the report in {out} has the counts")
    return summary


# ------------------------------------------------------------------------------------------------- the phases
def simulate_phase(cfg: BenchConfig, out: Path, say: Callable[[str], None]) -> tuple[BenchRun, Path, Path]:
    """1. The truth, and the files the emulated sensor starts from: ``sensor-replay.csv`` (both phases and the
    spare frames) and ``nominal.json`` (its factory parameters); ``true-camera.json`` beside them."""
    t = time.perf_counter()
    nominal = bench_nominal(cfg)
    cal_sim, drift_sim = simulate_phases(cfg)
    replay = concatenate_sessions(cal_sim.session, drift_sim.session, drift_first_frame(cfg))
    replay_path, nominal_path = out / "sensor-replay.csv", out / "nominal.json"
    write_session(replay_path, sensor_reference_session(replay, cfg.site, cfg.weather, cfg.precision))
    save_params(out / "true-camera.json", cfg.camera)
    save_params(nominal_path, nominal)
    run = BenchRun(cfg=cfg, nominal=nominal, cal_sim=cal_sim, drift_sim=drift_sim, spare_frames=spare_frames(cfg))
    run.replay_frames = int(np.unique(replay.frame).size)
    detail = f"{cfg.cal_frames} + {cfg.drift_frames} (+ {run.spare_frames} spare) frames, {len(replay)} stars"
    run.phases.append(Phase("simulate", time.perf_counter() - t, detail))
    say(f"[1/6] simulated {cfg.cal_frames} calibration + {cfg.drift_frames} drift frames ({len(replay)} stars)")
    return run, replay_path, nominal_path


def stream_calibration_phase(
    run: BenchRun, link: Link, t_start: float, out: Path, say: Callable[[str], None], show_progress: bool
) -> Session:
    """2. Stream the calibration phase (timed from ``t_start``, the sensor's launch); it is written to
    ``session.csv`` and returned. Fewer frames than asked for is a LinkError."""
    from hostlink.links.operations import frames_to_session

    cfg = run.cfg
    with progress_bar("streaming calibration frames", cfg.cal_frames, show_progress) as advance:
        frames, run.cal_estimates, _, run.cal_stream = stream_phase(
            link, cfg.cal_frames, cfg.poll_every_frames, advance, run.replay_frames
        )
    lost = run.cal_stream.lost_on_link
    if not run.cal_stream.complete:
        raise LinkError(
            f"the sensor sent {len(frames)} of {cfg.cal_frames} calibration frames ({lost} lost on the link"
            f"{', then its replay ran out' if run.cal_stream.ended_early else ''})"
        )
    streamed = frames_to_session(frames)
    write_session(out / "session.csv", streamed)
    detail = f"{len(frames)} frames, {len(streamed)} stars, {lost} lost"
    run.phases.append(Phase("stream", time.perf_counter() - t_start, detail))
    say(f"      streamed {len(frames)} frames / {len(streamed)} stars, {lost} messages lost")
    return streamed


def calibrate_phase(run: BenchRun, streamed: Session, out: Path, say: Callable[[str], None]) -> None:
    """3. Bundle-adjust the streamed session from the nominal camera; the result goes to ``calibrated.json``.
    A calibration the data cannot support is a one-line UserError (nothing is uploaded)."""
    from hostlink.calibration.data import calibration_data_from_session
    from hostlink.calibration.report import principal_point_prism_note
    from hostlink.calibration.run import calibrate, result_extras

    t = time.perf_counter()
    cfg = run.cfg
    run.data, run.ref_info = calibration_data_from_session(streamed, cfg.site, cfg.weather)
    try:
        run.outcome = calibrate(run.data, run.nominal, "bundle", noise_px=None)
    except ValueError as exc:  # what the streamed data cannot support (e.g. a nominal far from the camera)
        raise UserError(f"calibration failed: {exc}") from None
    save_params(out / "calibrated.json", run.outcome.params, result_extras(run.outcome))
    run.phases.append(Phase("calibrate", time.perf_counter() - t, f"bundle, {len(run.outcome.history)} iterations"))
    say(f"[3/6] calibrated: residual {run.outcome.before['rms_px']:.3f} -> {run.outcome.after['rms_px']:.4f} px RMS")
    note = principal_point_prism_note(run.outcome.degeneracies.get("principal_point_prism", []))
    if note is not None:
        say(f"      {note}")


def upload_phase(run: BenchRun, link: Link, generation_before: int, say: Callable[[str], None]) -> None:
    """4. The six-step safe upload of the calibrated set with its 1-sigma (the onboard estimator restarts from it as
    its prior), then the active set read back."""
    from hostlink.links.operations import read_active_params, safe_upload
    from onboard.prior import sigma_from_dict

    t = time.perf_counter()
    run.uploaded = safe_upload(
        link,
        run.outcome.params,
        step=lambda k, text: run.upload_steps.append(f"{k}. {text}"),
        sigma=sigma_from_dict(run.outcome.sigma()),
    )
    run.active = read_active_params(link)
    run.phases.append(Phase("upload", time.perf_counter() - t, f"generation {run.uploaded.generation}"))
    say(f"[4/6] uploaded and verified: generation {generation_before} -> {run.uploaded.generation}")


def track_phase(run: BenchRun, link: Link, say: Callable[[str], None], show_progress: bool) -> None:
    """5. The onboard estimator runs on through the drift phase while the host streams and polls it."""
    t = time.perf_counter()
    cfg = run.cfg
    with progress_bar("streaming drift frames", cfg.drift_frames, show_progress) as advance:
        frames, run.drift_estimates, run.drift_work, run.drift_stream = stream_phase(
            link, cfg.drift_frames, cfg.poll_every_frames, advance, run.replay_frames, drift_first_frame(cfg)
        )
    count = run.drift_stream
    run.drift_first_counter = int(frames[0].frame) if frames else None
    run.phases.append(Phase("track", time.perf_counter() - t, f"{count.received} of {count.expected} frames"))
    ran_out = ", then the sensor's replay ran out" if count.ended_early else ""
    say(
        f"[5/6] {count.received} of {count.expected} drift frames streamed ({count.lost_on_link} lost on the link"
        f"{ran_out}); the onboard estimator updated on {run.drift_work.updates} of the {run.drift_work.exposures} "
        f"exposures the sensor took ({len(run.drift_estimates)} estimates read)"
    )


# ------------------------------------------------------------------------------------------------- the pieces
def simulate_phases(cfg: BenchConfig) -> tuple[SimResult, SimResult]:
    """Calibration phase (static camera) + drift phase (sinusoidal focal drift), one continuous session: two
    ``SimResult``, each holding :func:`spare_frames` more frames than its phase (the drift phase starts at frame
    :func:`drift_first_frame`, that many seconds later)."""
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
    cal = simulate(SimConfig(frames=cfg.cal_frames + spare_frames(cfg), seed=cfg.seed, t0_iso=cfg.t0_iso, **common))
    drift = simulate(
        SimConfig(
            frames=cfg.drift_frames + spare_frames(cfg),
            seed=cfg.seed + 1000,
            t0_iso=iso_plus_seconds(cfg.t0_iso, float(drift_first_frame(cfg))),
            focal_drift_um=drift_amplitude_um(cfg),
            focal_drift_period_frames=cfg.drift_period_frames,
            **common,
        )
    )
    return cal, drift


def concatenate_sessions(first: Session, second: Session, frame_offset: int) -> Session:
    """One session: ``second``'s frame numbers shifted by ``frame_offset`` and appended to ``first``."""

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


def sensor_reference_session(
    session: Session, site: Site | None, weather: Weather | None, precision: str = "float32"
) -> Session:
    """The replay file the emulated sensor holds: a ground sensor turns its catalogue directions into observed ones
    itself (diurnal aberration, then refraction: seed 001 sec. 4, ``onboard.refraction.topocentric_observed``), so
    its recursive estimator sees corrected references; a ``precision="fixed"`` sensor does so in integers
    (``topocentric_observed_fixed``)."""
    if site is None:
        return session
    from hostlink.sky.references import session_references, session_with_references
    from onboard.fixedpoint import FixedRangeError

    try:
        references = session_references(
            session, site, weather, precision="fixed" if precision == "fixed" else "float64"
        )
    except FixedRangeError as exc:
        raise UserError(f"--precision fixed: the site correction is outside the fixed-point range: {exc}") from None
    return session_with_references(session, references)


def stream_phase(
    link: Link,
    n_frames: int,
    poll_every: int,
    progress: Callable[[int], None],
    source_frames: int | None = None,
    phase_first_frame: int = 0,
) -> tuple[list[CentroidFrame], list[tuple[int, Estimate]], EstimatorWork, StreamCount]:
    """Stream ``n_frames`` frames through the one stream loop (``hostlink.links.operations.stream_frames``), reading
    the onboard estimate every ``poll_every`` frames and once more at the end of the phase.

    Returns (frames, estimates, work, count) where estimates are (frame counter of the estimate's last update,
    Estimate), ``work`` (:class:`EstimatorWork`) counts the phase's exposures and estimator updates (from the status)
    and ``count`` (:class:`StreamCount`) where the frames went; ``source_frames``, the frames of the sensor's
    replay, and ``phase_first_frame``, the phase's first frame counter in it (the sensor skips to it:
    ``--phase-start``), give how many it still held at the start."""
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
    count = StreamCount(
        expected=int(n_frames),
        received=int(result.frames_received),
        lost_on_link=int(result.lost_messages),
        exposures=exposures,
        held_at_start=None
        if source_frames is None
        else int(source_frames) - max(int(before.frames_processed), int(phase_first_frame)),
        ended_early=bool(result.ended),
    )
    return result.frames, estimates, EstimatorWork(exposures=exposures, updates=updates), count
