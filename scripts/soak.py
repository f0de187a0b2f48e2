"""Soak of an emulated sensor doing its full work and a host watching it: memory must stay flat (issue 15).

    python scripts/soak.py                                  # 30 minutes on serial, RSS sampled every 10 s
    python scripts/soak.py --duration-s 120 --transport can --sample-s 5

Starts ``hostlink emulate`` (simulated sky, cycled; the onboard recursive estimator on, so every exposure the
modelled processor has time for goes through the estimator, the firmware's full work) and ``hostlink monitor``
(centroid stream on, an estimate poll every ``--interval-s``), both as separate processes as a user runs them. Every
``--sample-s`` it reads the resident set size of both processes (``VmRSS`` in ``/proc/PID/status``) and the monitor's
last poll (frames received, estimator updates).

The first ``--warmup-s`` seconds are not judged: imports, the simulator's star catalogue, the estimator's matrices
and Python's allocator arenas settle there. After it, the drift of a process is its highest RSS minus its RSS at the
end of the warm-up. One JSON line per sample with ``--verbose``, then a summary line; exit code 1 if either drift
exceeds ``--max-drift-mb`` (default 5 MB), if either process ended early, or if the estimator stopped updating (a
soak of an idle sensor proves nothing: the estimator must have made at least ``--min-update-fraction`` of an update
per frame received after the warm-up).

Linux only (``/proc``). The short version runs in CI as tests/test_soak_short.py.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from hostlink.emulator.process import EmulatorProcess


def rss_mb(pid: int) -> float | None:
    """Resident set size of process ``pid`` [MB = 2^20 bytes], from ``VmRSS`` in /proc/PID/status (reported in kB);
    None once the process has ended (no such file, or a zombie's status without VmRSS)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return None
    for line in text.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return None


class MonitorReader:
    """Reads ``hostlink monitor --json`` lines in a thread and keeps the last poll with an estimate."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.last: dict = {}
        self.polls = 0
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            try:
                record = json.loads(line)
            except ValueError:
                continue
            self.polls += 1
            if record.get("estimate", True) is not None:
                self.last = record


@dataclass
class SoakResult:
    transport: str
    duration_s: float
    warmup_s: float
    samples: int
    emulator_rss_after_warmup_mb: float
    monitor_rss_after_warmup_mb: float
    emulator_drift_mb: float
    monitor_drift_mb: float
    max_drift_mb: float
    frames_after_warmup: int
    updates_after_warmup: int
    polls: int
    failures: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.failures


def soak(
    duration_s: float = 1800.0,
    transport: str = "serial",
    sample_s: float = 10.0,
    warmup_s: float = 60.0,
    interval_s: float = 1.0,
    max_drift_mb: float = 5.0,
    min_update_fraction: float = 0.5,
    on_sample=None,  # noqa: ANN001 - callable(dict) per sample
    min_frames: int = 0,
    deadline_s: float | None = None,
) -> SoakResult:
    """Run the soak (module docstring) for ``duration_s`` [s] after the emulator is ready; returns the figures.
    ``min_frames``: go on past ``duration_s`` until the monitor has received that many frames after the warm-up (a
    slow, shared machine streams fewer per second), but not past ``deadline_s`` [s] (default 4 x duration_s)."""
    deadline_s = 4.0 * duration_s if deadline_s is None else deadline_s
    failures: list[str] = []
    with EmulatorProcess(transport) as emulator, tempfile.TemporaryFile("w+") as monitor_err:
        monitor = _start_monitor(emulator.link, interval_s, monitor_err)
        reader = MonitorReader(monitor)
        procs = {"emulator": emulator.process, "monitor": monitor}
        try:
            run = _sample(procs, reader, (duration_s, deadline_s, warmup_s, sample_s), min_frames, on_sample, failures)
        finally:
            _stop(monitor)
        end = dict(reader.last)
        if failures:
            monitor_err.seek(0)
            failures += [f"monitor: {line}" for line in monitor_err.read().strip().splitlines()[-1:]]
    if not run.base:
        failures.append(f"the soak ended before the warm-up ({warmup_s:g} s) was over")
        run.base = run.peak = {"emulator": float("nan"), "monitor": float("nan")}
    drift = {n: run.peak[n] - run.base[n] for n in run.base}
    frames = _frames(end) - _frames(run.at_warmup)
    updates = int(end.get("updates", 0)) - int(run.at_warmup.get("updates", 0))
    failures += _judged(drift, frames, updates, max_drift_mb, min_update_fraction)
    return SoakResult(
        transport=transport,
        duration_s=duration_s,
        warmup_s=warmup_s,
        samples=run.samples,
        emulator_rss_after_warmup_mb=round(run.base["emulator"], 2),
        monitor_rss_after_warmup_mb=round(run.base["monitor"], 2),
        emulator_drift_mb=round(drift["emulator"], 2),
        monitor_drift_mb=round(drift["monitor"], 2),
        max_drift_mb=max_drift_mb,
        frames_after_warmup=frames,
        updates_after_warmup=updates,
        polls=reader.polls,
        failures=failures,
    )


@dataclass
class _Samples:
    """What the sampling saw: RSS [MB] per process at the end of the warm-up (``base``, empty before it) and its
    highest since, the monitor's last poll at the end of the warm-up, and the number of samples."""

    base: dict[str, float] = field(default_factory=dict)
    peak: dict[str, float] = field(default_factory=dict)
    at_warmup: dict = field(default_factory=dict)
    samples: int = 0


def _start_monitor(link: str, interval_s: float, err) -> subprocess.Popen:
    """``hostlink monitor --json`` on ``link``, polling every ``interval_s`` [s], its stderr into the file ``err``."""
    return subprocess.Popen(
        [sys.executable, "-m", "hostlink.cli", "monitor", "--link", link, "--count", "0"]
        + ["--interval", str(interval_s), "--json", "--timeout", "10"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=err,  # a file, not a pipe nobody reads: a long run never stalls on it
        text=True,
    )


def _stop(monitor: subprocess.Popen) -> None:
    monitor.terminate()
    try:
        monitor.wait(timeout=20)
    except subprocess.TimeoutExpired:
        monitor.kill()
        monitor.wait()


def _sample(
    procs: dict[str, subprocess.Popen],
    reader: MonitorReader,
    times_s: tuple[float, float, float, float],
    min_frames: int,
    on_sample,  # noqa: ANN001 - callable(dict) per sample
    failures: list[str],
) -> _Samples:
    """Every ``sample_s`` until ``duration_s`` (and on until ``min_frames`` after the warm-up, up to
    ``deadline_s``; ``times_s`` = (duration_s, deadline_s, warmup_s, sample_s)), the processes' RSS; a process
    that ended is a failure and stops the sampling."""
    duration_s, deadline_s, warmup_s, sample_s = times_s
    run = _Samples()
    t0 = time.monotonic()
    while (now := time.monotonic() - t0) < duration_s or (
        now < deadline_s and _frames(reader.last) - _frames(run.at_warmup) < min_frames
    ):
        sampled = {name: rss_mb(p.pid) for name, p in procs.items()}
        ended = [n for n, p in procs.items() if p.poll() is not None]
        ended += [n for n, v in sampled.items() if v is None and n not in ended]
        if ended:
            failures.append(f"{', '.join(ended)} ended after {now:.0f} s")
            break
        rss = {name: float(v) for name, v in sampled.items()}
        run.samples += 1
        if now >= warmup_s:
            if not run.base:
                run.base, run.at_warmup = dict(rss), dict(reader.last)
            run.peak = {n: max(run.peak.get(n, 0.0), v) for n, v in rss.items()}
        if on_sample is not None:
            work = {k: reader.last.get(k) for k in ("frames_received", "updates")}
            on_sample({"t_s": round(now, 1), **{f"{n}_rss_mb": round(v, 2) for n, v in rss.items()}, **work})
        time.sleep(sample_s)  # the sampling period of a measurement, not a synchronisation
    return run


def _judged(
    drift: dict[str, float], frames: int, updates: int, max_drift_mb: float, min_update_fraction: float
) -> list[str]:
    """The failures of the judged window: a process whose RSS grew more than ``max_drift_mb``, or an estimator that
    updated on fewer than ``min_update_fraction`` of the frames (not at full work)."""
    failures = []
    for name, mb in drift.items():
        if not mb <= max_drift_mb:
            failures.append(f"{name} RSS grew {mb:.2f} MB after the warm-up (limit {max_drift_mb:g} MB)")
    if frames <= 0 or updates < min_update_fraction * frames:
        failures.append(f"the estimator made {updates} updates in {frames} frames after the warm-up: not at full work")
    return failures


def _frames(poll: dict) -> int:
    """Frames received by the monitor at a poll record (0 before the first)."""
    return int(poll.get("frames_received", 0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration-s", type=float, default=1800.0, help="soak length [s] (default 1800 = 30 min)")
    parser.add_argument("--transport", choices=("serial", "can", "modbus"), default="serial")
    parser.add_argument("--sample-s", type=float, default=10.0, help="RSS sampling period [s] (default 10)")
    parser.add_argument("--warmup-s", type=float, default=60.0, help="not judged at the start [s] (default 60)")
    parser.add_argument("--interval-s", type=float, default=1.0, help="monitor's poll period [s] (default 1)")
    parser.add_argument("--max-drift-mb", type=float, default=5.0, help="largest RSS growth allowed [MB] (default 5)")
    parser.add_argument("--min-update-fraction", type=float, default=0.5, help="estimator updates per frame, at least")
    parser.add_argument(
        "--min-frames", type=int, default=0, help="go on past --duration-s until this many frames after the warm-up"
    )
    parser.add_argument("--verbose", action="store_true", help="one JSON line per sample")
    args = parser.parse_args()
    if not Path("/proc/self/status").exists():
        parser.error("needs Linux /proc to read the processes' RSS")
    result = soak(
        args.duration_s,
        args.transport,
        args.sample_s,
        args.warmup_s,
        args.interval_s,
        args.max_drift_mb,
        args.min_update_fraction,
        on_sample=(lambda s: print(json.dumps(s), flush=True)) if args.verbose else None,
        min_frames=args.min_frames,
    )
    print(json.dumps({**asdict(result), "pass": result.passed}), flush=True)
    return 0 if result.passed else 1


if __name__ == "__main__":
    sys.exit(main())
