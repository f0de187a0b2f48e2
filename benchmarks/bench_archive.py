"""Benchmark of archives at scale (issue 12): sessions of 10^3 to 10^6 frames read in chunks, CSV against Parquet,
and ``hostlink replay`` streaming them, run on demand.

1. Sessions: seed 004's camera, 10-30 stars per frame uniform over the detector, 0.05 px noise, frames 0.1 s
   apart, reference directions in ``ra_deg``/``dec_deg`` (hostlink.api.synthetic_session: the camera model and a
   random attitude per frame, so any number of frames is cheap; every row is a valid session row). Written once
   per size as CSV and as Parquet through the one session writer (``SessionWriter``, chunk by chunk), kept in
   ``--dir`` and reused.
2. Reading, each in its own child process (peak memory = the child's peak resident set, VmHWM, with the
   interpreter and libraries: what a user's machine must have): ``read_session_chunks`` over the whole file (CSV
   and Parquet: seconds (the fastest of 3), rows/s, MB/s of file) and, up to ``--in-memory-max`` frames,
   ``read_session`` (the whole session in memory).
3. Replay, in a child process: the ``hostlink replay`` command itself (``--trace`` written), with the onboard
   estimator's own time measured inside the same run: every call of ``onboard.firmware.estimator_update`` (what the
   sensor runs per frame: the onboard update alone, over the same frames) is timed, in wall time and in process CPU
   time (the machine's other load inflates wall time, not CPU time). The ratio replay frame rate / the estimator's
   own frame rate = estimator time / replay time, in the same run (acceptance: >= 0.80, and peak < 300 MB at 10^6
   frames; the report takes the lower of the wall and the CPU ratio). Up to ``--in-memory-max`` frames the
   in-memory path (``read_session`` + ``replay_session`` + ``write_trace``) runs beside it, and the streamed /
   in-memory ratios of time, CPU time and peak memory are printed, with whether both give the same estimate.

Usage: nice -n 10 .venv/bin/python benchmarks/bench_archive.py [--sizes 1000,10000,100000] [--dir DIR]
           [--replay-formats parquet,csv] [--in-memory-max 100000] [--no-replay] [--no-read]
           [--replay-time-limit SECONDS] [--json RESULTS.json]
At 10^6 frames (about 20 min of one core for the estimator alone): ``--sizes 1000000 --no-read``.
The Parquet writer and reader are those of hostlink/files/columnar.py; the CSV reader is pyarrow's streaming CSV
reader behind the same checks (hostlink/files/session/).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from hostlink.api import synthetic_session
from hostlink.files.params import load_params
from hostlink.files.session import Session, SessionWriter
from onboard.camera import unit_to_radec

TRUTH = "builtin:seed004_camera"
NOMINAL = "builtin:seed004_nominal"
#: Frames generated at a time (bounds the generator's memory).
GENERATE_CHUNK_FRAMES = 10_000
T0 = np.datetime64("2026-03-14T02:00:00.000", "ms")
FRAME_INTERVAL_MS = 100
#: Reads of each file, the fastest reported: the machine's other load only ever slows a read down.
READ_REPEATS = 3
#: Frames between the progress samples a replay child writes (frames, seconds, estimator seconds, peak memory).
PROGRESS_FRAMES = int(os.environ.get("BENCH_ARCHIVE_PROGRESS_FRAMES", "10000"))


def synthetic_chunks(n_frames: int, seed: int = 0, chunk_frames: int = GENERATE_CHUNK_FRAMES):
    """Consecutive Sessions of ``chunk_frames`` frames (item 1 of the module docstring)."""
    truth = load_params(TRUTH)
    for k, first in enumerate(range(0, n_frames, chunk_frames)):
        m = min(chunk_frames, n_frames - first)
        data = synthetic_session(truth, m, seed=seed * 1_000_003 + k).data
        counts = np.diff(data.frame_starts)
        frame = np.repeat(np.arange(first, first + m, dtype=np.int64), counts)
        when = T0 + (frame * FRAME_INTERVAL_MS).astype("timedelta64[ms]")
        t_utc = np.char.add(np.datetime_as_string(when, unit="ms"), "Z").astype(object)
        ra_rad, dec_rad = unit_to_radec(data.r)
        yield Session(
            frame=frame,
            t_utc=t_utc,
            star_id=data.star_id.astype(np.int64),
            x_px=data.x_px,
            y_px=data.y_px,
            ra_deg=np.degrees(ra_rad) % 360.0,
            dec_deg=np.degrees(dec_rad),
        )


def write_synthetic_session(path: Path, n_frames: int, seed: int = 0) -> float:
    """Write a synthetic session of ``n_frames`` frames to ``path`` (CSV or .parquet); returns seconds taken."""
    t = time.perf_counter()
    with SessionWriter(path) as writer:
        for chunk in synthetic_chunks(n_frames, seed):
            writer.append(chunk)
    return time.perf_counter() - t


def _peak_mb() -> float:
    """This process's peak resident memory [MB]: VmHWM of /proc/self/status (Linux; the high-water mark of this
    process's own memory: ``ru_maxrss`` would carry the parent's from before ``exec``), else ``ru_maxrss``."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    import resource

    scale = 1.0 if sys.platform == "darwin" else 1024.0  # bytes on macOS, kB elsewhere
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale / 1024.0


# --------------------------------------------------------------------------------------------- child processes
def child_read(path: str, whole: bool, repeats: int = READ_REPEATS) -> dict:
    """Read ``path`` ``repeats`` times (in chunks, or whole); the fastest wall time and CPU time (process, every
    thread) of a read."""
    from hostlink.files.session import read_session, read_session_chunks

    best, best_cpu = float("inf"), float("inf")
    for _ in range(repeats):
        t, cpu = time.perf_counter(), time.process_time()
        if whole:
            session = read_session(path)
            rows, frames = len(session), session.n_frames
            del session
        else:
            rows = frames = 0
            for chunk in read_session_chunks(path):
                rows += len(chunk)
                frames += chunk.n_frames
        best, best_cpu = min(best, time.perf_counter() - t), min(best_cpu, time.process_time() - cpu)
    return {"seconds": best, "cpu_seconds": best_cpu, "rows": rows, "frames": frames, "maxrss_mb": _peak_mb()}


def child_replay(path: str, out_dir: str, in_memory: bool) -> dict:
    """One replay (``hostlink replay`` streaming, or the in-memory path) with every call of the onboard update timed:
    wall time (``perf_counter``) and the process CPU time (``process_time``, every thread: what the machine's other
    load does not inflate), for the run and for the estimator alone, on the same frames."""
    from onboard import firmware

    spent = [0.0, 0, 0.0]  # estimator wall seconds, frames, estimator CPU seconds
    update = firmware.estimator_update
    t, cpu = time.perf_counter(), time.process_time()

    def timed_update(*args, **kwargs):
        t_frame, cpu_frame = time.perf_counter(), time.process_time()
        try:
            return update(*args, **kwargs)
        finally:
            spent[0] += time.perf_counter() - t_frame
            spent[2] += time.process_time() - cpu_frame
            spent[1] += 1
            if spent[1] % PROGRESS_FRAMES == 0:  # a sample of the run so far, on stderr, for --replay-time-limit
                sample = {
                    "frames": spent[1],
                    "seconds": time.perf_counter() - t,
                    "estimator_seconds": spent[0],
                    "cpu_seconds": time.process_time() - cpu,
                    "estimator_cpu_seconds": spent[2],
                }
                print(json.dumps(sample | {"maxrss_mb": _peak_mb()}), file=sys.stderr, flush=True)

    firmware.estimator_update = timed_update
    out, trace = os.path.join(out_dir, "estimate.json"), os.path.join(out_dir, "trace.csv")
    if in_memory:
        from hostlink.calibration.replay import replay_session
        from hostlink.files.session import read_session
        from hostlink.files.trace import write_trace

        result = replay_session(read_session(path), load_params(NOMINAL))
        write_trace(trace, result.trace)
        focal_mm = result.params.focal_length_mm
    else:
        from hostlink.cli import main

        with open(os.devnull, "w") as quiet:
            stdout, sys.stdout = sys.stdout, quiet
            try:
                code = main(["replay", path, "--nominal", NOMINAL, "--out", out, "--trace", trace])
            finally:
                sys.stdout = stdout
        if code != 0:
            raise SystemExit(f"hostlink replay failed ({code})")
        focal_mm = json.loads(Path(out).read_text())["focal_length_mm"]
    return {
        "seconds": time.perf_counter() - t,
        "cpu_seconds": time.process_time() - cpu,
        "estimator_seconds": spent[0],
        "estimator_cpu_seconds": spent[2],
        "frames": spent[1],
        "maxrss_mb": _peak_mb(),
        "focal_length_mm": focal_mm,
    }


def run_child(*args: str, time_limit_s: float | None = None) -> dict:
    """Run this file as a child (``--child ...``) and return the JSON it prints. With ``time_limit_s`` the child is
    stopped then, and the last progress sample it wrote (stderr) comes back with ``"partial": True``."""
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    timer = threading.Timer(time_limit_s, proc.kill) if time_limit_s else None
    if timer is not None:
        timer.start()
    samples, other = [], []
    for line in proc.stderr:
        (samples if line.startswith('{"frames"') else other).append(line)
        if time_limit_s and line.startswith('{"frames"'):
            print(f"  progress: {line.strip()}", flush=True)  # a long run's memory and rate as it goes
    stdout = proc.stdout.read()
    code = proc.wait()
    if timer is not None:
        timer.cancel()
    if code != 0 and time_limit_s and samples:
        return json.loads(samples[-1]) | {"partial": True}
    if code != 0:
        raise SystemExit(f"child {args} failed:\n{''.join(other)}")
    return json.loads(stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------------------------ report
#: Acceptance of issue 12 for ``replay`` (10^6 frames): peak memory [MB] and the least share of the estimator's own
#: frame rate.
ACCEPT_PEAK_MB = 300.0
ACCEPT_SHARE = 0.80


def _replay_line(r: dict) -> str:
    """One replay's figures: frame rates of the run and of the estimator alone (wall and CPU), their ratio (the
    share), peak memory."""
    share, cpu_share = r["estimator_seconds"] / r["seconds"], r["estimator_cpu_seconds"] / r["cpu_seconds"]
    done = f"PARTIAL: stopped after {r['frames']} frames" if r.get("partial") else f"f {r['focal_length_mm']:.6f} mm"
    return (
        f"{r['seconds']:8.1f} s ({r['cpu_seconds']:7.1f} s CPU)  {r['frames'] / r['seconds']:6.0f} frames/s, "
        f"estimator alone {r['frames'] / r['estimator_seconds']:6.0f} frames/s: ratio {share:6.1%} "
        f"(CPU: {r['frames'] / r['cpu_seconds']:6.0f} vs {r['frames'] / r['estimator_cpu_seconds']:6.0f} frames/s, "
        f"ratio {cpu_share:6.1%})  peak {r['maxrss_mb']:5.0f} MB  {done}"
    )


def _acceptance(last: dict) -> None:
    """The acceptance figures at the largest size run: peak memory and frame-rate ratio of the streamed replay."""
    r = last["streamed"]
    share = min(r["estimator_seconds"] / r["seconds"], r["estimator_cpu_seconds"] / r["cpu_seconds"])
    print(
        f"\nacceptance at {last['frames']} frames ({last['format']}"
        + (", PARTIAL run" if r.get("partial") else "")
        + f"): peak {r['maxrss_mb']:.0f} MB / {ACCEPT_PEAK_MB:.0f} MB = {r['maxrss_mb'] / ACCEPT_PEAK_MB:.2f} "
        f"({'ok' if r['maxrss_mb'] < ACCEPT_PEAK_MB else 'NOT met'}); frame rate / the estimator's own = "
        f"{share:.3f} (the lower of wall and CPU) against {ACCEPT_SHARE:.2f} "
        f"({'ok' if share >= ACCEPT_SHARE else 'NOT met'})"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,10000,100000", help="frames per session, comma-separated")
    ap.add_argument("--dir", default="bench-archive", help="where the sessions are written (and reused)")
    ap.add_argument("--replay-formats", default="parquet", help="formats replayed: parquet, csv or both")
    ap.add_argument("--in-memory-max", type=int, default=100_000, help="largest session also run in memory")
    ap.add_argument("--no-replay", action="store_true", help="reading only")
    ap.add_argument("--no-read", action="store_true", help="replay only")
    ap.add_argument(
        "--replay-time-limit",
        type=float,
        help="stop a replay after this many seconds and report it as partial (frames done, peak so far)",
    )
    ap.add_argument("--json", metavar="RESULTS.json", help="also write every replay figure to this file")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return 0

    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    sizes = [int(s) for s in args.sizes.split(",")]
    formats = [f.strip() for f in args.replay_formats.split(",")]
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, pid {os.getpid()}, sessions in {base}")
    results: list[dict] = []
    for n in sizes:
        files = _session_files(base, n, formats if args.no_read else ("csv", "parquet"))
        print(f"\n== {n} frames ==")
        if not args.no_read:
            _print_reads(files, n <= args.in_memory_max)
        if args.no_replay:
            continue
        for fmt in formats:
            results.append(_replays(base, n, fmt, files[fmt], n <= args.in_memory_max, args.replay_time_limit))
    if results:
        _acceptance(results[-1])
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


def _child(kind: str, *rest: str) -> None:
    """The child process's job (``--child``): one read or one replay, its figures printed as JSON."""
    if kind == "read":
        print(json.dumps(child_read(rest[0], rest[1] == "whole")))
    else:
        print(json.dumps(child_replay(rest[0], rest[1], rest[2] == "memory")))


def _session_files(base: Path, n: int, formats) -> dict[str, Path]:
    """The synthetic session of ``n`` frames in each format, written into ``base`` unless there already."""
    files = {}
    for fmt in formats:
        path = base / f"session_{n}.{fmt}"
        if not path.exists():
            seconds = write_synthetic_session(path, n)
            print(f"[{n} frames] wrote {path} in {seconds:.1f} s")
        files[fmt] = path
    return files


def _print_reads(files: dict[str, Path], whole: bool) -> None:
    """Each file read in chunks (and, with ``whole``, at once) in a child process: time, rate and peak memory."""
    for fmt, path in files.items():
        size_mb = path.stat().st_size / 1e6
        r = run_child("read", str(path), "chunks")
        print(
            f"read {fmt:7s} in chunks: {r['seconds']:7.2f} s ({r['cpu_seconds']:6.2f} s CPU)  "
            f"{r['rows'] / r['seconds'] / 1e6:5.2f} M rows/s ({r['rows'] / r['cpu_seconds'] / 1e6:5.2f} of CPU)  "
            f"{size_mb / r['seconds']:6.1f} MB/s of {size_mb:7.1f} MB  peak {r['maxrss_mb']:6.0f} MB"
        )
        if whole:
            w = run_child("read", str(path), "whole")
            print(
                f"read {fmt:7s} whole:     {w['seconds']:7.2f} s ({w['cpu_seconds']:6.2f} s CPU)  "
                f"peak {w['maxrss_mb']:6.0f} MB"
            )


def _replays(base: Path, n: int, fmt: str, path: Path, in_memory: bool, time_limit_s: float | None) -> dict:
    """The session ``path`` replayed streamed (and, with ``in_memory``, in memory, side by side) in child
    processes, each printed; the figures as one result record."""
    out = base / f"replay_{n}_{fmt}"
    out.mkdir(exist_ok=True)
    streamed = run_child("replay", str(path), str(out), "stream", time_limit_s=time_limit_s)
    runs = [("streamed", streamed)]
    if in_memory:
        runs.append(("in memory", run_child("replay", str(path), str(out), "memory")))
    for label, r in runs:
        print(f"replay {fmt:7s} {label:9s}: " + _replay_line(r))
    if len(runs) == 2:
        s, m = streamed, runs[1][1]
        print(
            f"replay {fmt:7s} streamed / in memory: time x{s['seconds'] / m['seconds']:.3f} (CPU "
            f"x{s['cpu_seconds'] / m['cpu_seconds']:.3f}), peak x{s['maxrss_mb'] / m['maxrss_mb']:.3f}"
            f" ({s['maxrss_mb']:.0f} / {m['maxrss_mb']:.0f} MB), same estimate: "
            f"{s['focal_length_mm'] == m['focal_length_mm']}"
        )
    return {"frames": n, "format": fmt, "streamed": streamed} | ({"in_memory": runs[1][1]} if len(runs) == 2 else {})


if __name__ == "__main__":
    sys.exit(main())
