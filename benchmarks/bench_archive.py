"""Benchmark of archives at scale (issue 12): sessions of 10^3 to 10^6 frames read in chunks, CSV against Parquet,
and ``hostlink replay`` streaming them, run on demand.

1. Sessions: seed 004's camera, 10-30 stars per frame uniform over the detector, 0.05 px noise, frames 0.1 s
   apart, reference directions in ``ra_deg``/``dec_deg`` (tests/synthetic_sessions.py: the camera model and a
   random attitude per frame, so any number of frames is cheap; every row is a valid session row). Written once
   per size as CSV and as Parquet through the one session writer (``SessionWriter``, chunk by chunk), kept in
   ``--dir`` and reused.
2. Reading, each in its own child process (peak memory = the child's peak resident set, VmHWM, with the
   interpreter and libraries: what a user's machine must have): ``read_session_chunks`` over the whole file (CSV
   and Parquet: seconds (the fastest of 3), rows/s, MB/s of file) and, up to 10 x ``--in-memory-max`` frames,
   ``read_session`` (the whole session in memory).
3. Replay, in a child process: the ``hostlink replay`` command itself (``--trace`` written), with the onboard
   estimator's own time measured inside the same run: every call of ``onboard.firmware.estimator_update`` (what the
   sensor runs per frame) is timed. ``estimator share`` = estimator time / wall time = replay frame rate / the
   estimator's own frame rate, on the same frames in the same run (acceptance: >= 0.80, peak < 300 MB at 10^6
   frames). Up to ``--in-memory-max`` frames the in-memory path (``read_session`` + ``replay_session`` +
   ``write_trace``) runs beside it.

Usage: nice -n 10 .venv/bin/python benchmarks/bench_archive.py [--sizes 1000,10000,100000] [--dir DIR]
           [--replay-formats parquet,csv] [--in-memory-max 10000] [--no-replay]
The Parquet writer and reader are those of hostlink/files/columnar.py; the CSV reader is pyarrow's streaming CSV
reader behind the same checks (hostlink/files/session.py).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the synthetic star fields live there

from synthetic_sessions import synthetic_session  # noqa: E402

from hostlink.files.params import load_params  # noqa: E402
from hostlink.files.session import Session, SessionWriter  # noqa: E402
from onboard.camera import unit_to_radec  # noqa: E402

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
    from hostlink.files.session import read_session, read_session_chunks

    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        if whole:
            session = read_session(path)
            rows, frames = len(session), session.n_frames
            del session
        else:
            rows = frames = 0
            for chunk in read_session_chunks(path):
                rows += len(chunk)
                frames += chunk.n_frames
        best = min(best, time.perf_counter() - t)
    return {"seconds": best, "rows": rows, "frames": frames, "maxrss_mb": _peak_mb()}


def child_replay(path: str, out_dir: str, in_memory: bool) -> dict:
    from onboard import firmware

    spent = [0.0, 0]
    update = firmware.estimator_update
    t = time.perf_counter()

    def timed_update(*args, **kwargs):
        t_frame = time.perf_counter()
        try:
            return update(*args, **kwargs)
        finally:
            spent[0] += time.perf_counter() - t_frame
            spent[1] += 1
            if spent[1] % PROGRESS_FRAMES == 0:  # a sample of the run so far, on stderr, for --replay-time-limit
                sample = {"frames": spent[1], "seconds": time.perf_counter() - t, "estimator_seconds": spent[0]}
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
    wall = time.perf_counter() - t
    return {
        "seconds": wall,
        "estimator_seconds": spent[0],
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
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,10000,100000", help="frames per session, comma-separated")
    ap.add_argument("--dir", default="bench-archive", help="where the sessions are written (and reused)")
    ap.add_argument("--replay-formats", default="parquet", help="formats replayed: parquet, csv or both")
    ap.add_argument("--in-memory-max", type=int, default=10_000, help="largest session also run in memory")
    ap.add_argument("--no-replay", action="store_true", help="reading only")
    ap.add_argument("--no-read", action="store_true", help="replay only")
    ap.add_argument(
        "--replay-time-limit",
        type=float,
        help="stop a replay after this many seconds and report it as partial (frames done, peak so far)",
    )
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        kind, *rest = args.child
        if kind == "read":
            print(json.dumps(child_read(rest[0], rest[1] == "whole")))
        else:
            print(json.dumps(child_replay(rest[0], rest[1], rest[2] == "memory")))
        return 0

    base = Path(args.dir)
    base.mkdir(parents=True, exist_ok=True)
    sizes = [int(s) for s in args.sizes.split(",")]
    formats = [f.strip() for f in args.replay_formats.split(",")]
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, pid {os.getpid()}, sessions in {base}")
    for n in sizes:
        files = {}
        for fmt in ("csv", "parquet"):
            path = base / f"session_{n}.{fmt}"
            if not path.exists():
                seconds = write_synthetic_session(path, n)
                print(f"[{n} frames] wrote {path} in {seconds:.1f} s")
            files[fmt] = path
        print(f"\n== {n} frames ==")
        for fmt, path in files.items() if not args.no_read else ():
            size_mb = path.stat().st_size / 1e6
            r = run_child("read", str(path), "chunks")
            print(
                f"read {fmt:7s} in chunks: {r['seconds']:7.2f} s  {r['rows'] / r['seconds'] / 1e6:5.2f} M rows/s  "
                f"{size_mb / r['seconds']:6.1f} MB/s of {size_mb:7.1f} MB  peak {r['maxrss_mb']:6.0f} MB"
            )
            if n <= 10 * args.in_memory_max:
                w = run_child("read", str(path), "whole")
                print(f"read {fmt:7s} whole:     {w['seconds']:7.2f} s  peak {w['maxrss_mb']:6.0f} MB")
        if args.no_replay:
            continue
        for fmt in formats:
            out = base / f"replay_{n}_{fmt}"
            out.mkdir(exist_ok=True)
            streamed = run_child("replay", str(files[fmt]), str(out), "stream", time_limit_s=args.replay_time_limit)
            runs = [("streamed", streamed)]
            if n <= args.in_memory_max:
                runs.append(("in memory", run_child("replay", str(files[fmt]), str(out), "memory")))
            for label, r in runs:
                share = r["estimator_seconds"] / r["seconds"]
                print(
                    f"replay {fmt:7s} {label:9s}: {r['seconds']:8.1f} s  {r['frames'] / r['seconds']:7.0f} frames/s  "
                    f"estimator alone {r['frames'] / r['estimator_seconds']:7.0f} frames/s  share {share:5.1%}  "
                    f"peak {r['maxrss_mb']:6.0f} MB  "
                    + (
                        f"PARTIAL: stopped after {r['frames']} frames"
                        if r.get("partial")
                        else f"f {r['focal_length_mm']:.6f} mm"
                    )
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
