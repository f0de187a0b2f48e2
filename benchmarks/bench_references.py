"""Benchmark (not a test) of the reference directions a session without ``ra_deg``/``dec_deg`` needs (issue 29 item
2): the same session, with and without those columns, through ``hostlink calibrate``, ``attitude`` and ``replay``,
measured side by side in fresh processes.

A session streamed from a sensor carries star ids and no reference directions; the host then computes each star's
geocentric apparent place at its frame's time (``hostlink.sky.apparent.apparent_directions``: ERFA per star at
nodes an hour apart, interpolated). With the columns, the file's directions are used as they are. The ratio
without / with is what a user of stream -> calibrate pays for not having them.

The session is seed 004's simulated setup (10-30 stars a frame, 0.05 px, frames 0.1 s apart; ``hostlink.sky
.simulate``), written once as CSV with the columns and once without, kept in ``--dir`` and reused. Each command runs
``--repeat`` times alternating with/without; the best wall time of each is reported (and the CPU time of that run).

    .venv/bin/python benchmarks/bench_references.py [--frames 100000] [--replay-frames 10000] [--repeat 1]
        [--commands calibrate,attitude,replay] [--dir /tmp/bench-references]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from hostlink.api import read_session, seed004_config, simulate, write_session

NOMINAL = "builtin:seed004_nominal"
TRUE_CAMERA = "builtin:seed004_camera"


def sessions(directory: Path, n_frames: int) -> tuple[Path, Path]:
    """(with columns, without columns) CSV files of one simulated session of ``n_frames`` frames."""
    with_cols = directory / f"with-{n_frames}.csv"
    without = directory / f"without-{n_frames}.csv"
    if not (with_cols.is_file() and without.is_file()):
        session = simulate(seed004_config(n_frames, seed=29)).session
        write_session(with_cols, session)
        write_session(without, replace(session, ra_deg=None, dec_deg=None))
    return with_cols, without


def first_frames(path: Path, n_frames: int, out: Path) -> Path:
    """The first ``n_frames`` frames of a session file (replay's estimator is slower per frame)."""
    if not out.is_file():
        session = read_session(path)
        end = int(session.frame_starts[n_frames]) if n_frames < session.n_frames else len(session)
        write_session(out, session.select(range(end)))
    return out


def timed(command: list[str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one ``hostlink`` command in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "hostlink.cli", *command], capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"hostlink {' '.join(command)} failed: {done.stderr.strip()}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def command_line(name: str, session: Path, directory: Path, params: Path) -> list[str]:
    quiet = ["--quiet"]
    if name == "calibrate":
        return ["calibrate", str(session), "--nominal", NOMINAL, "--out", str(directory / "cal.json"), *quiet]
    if name == "attitude":
        return ["attitude", str(session), "--params", str(params), "--out", str(directory / "att.csv")]
    if name == "replay":
        return ["replay", str(session), "--nominal", NOMINAL, "--out", str(directory / "est.json")]
    raise SystemExit(f"unknown command {name!r}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--replay-frames", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--commands", default="calibrate,attitude,replay")
    parser.add_argument("--dir", default="/tmp/bench-references")
    args = parser.parse_args()
    directory = Path(args.dir)
    directory.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PYTHONPATH", str(Path(__file__).resolve().parents[1]))

    t = time.perf_counter()
    with_cols, without = sessions(directory, args.frames)
    print(f"sessions of {args.frames} frames ready in {time.perf_counter() - t:.1f} s ({directory})")
    params = directory / "true-camera.json"
    if not params.is_file():
        example = [sys.executable, "-m", "hostlink.cli", "example", str(directory / "example")]
        subprocess.run(example, check=True, capture_output=True)
        params.write_bytes((directory / "example" / "true-camera.json").read_bytes())

    print(f"{'command':<10} {'frames':>8} {'with [s]':>10} {'without [s]':>12} {'ratio':>6}   CPU with / without [s]")
    for name in args.commands.split(","):
        files = (with_cols, without)
        n = args.frames
        if name == "replay" and args.replay_frames < args.frames:
            n = args.replay_frames
            files = tuple(first_frames(f, n, directory / f"{f.stem}-first-{n}.csv") for f in files)
        best = {}
        for _ in range(args.repeat):
            for label, path in zip(("with", "without"), files, strict=True):
                result = timed(command_line(name, path, directory, params))
                if label not in best or result[0] < best[label][0]:
                    best[label] = result
        (w_wall, w_cpu), (o_wall, o_cpu) = best["with"], best["without"]
        print(f"{name:<10} {n:>8} {w_wall:>10.2f} {o_wall:>12.2f} {o_wall / w_wall:>6.2f}   {w_cpu:.2f} / {o_cpu:.2f}")


if __name__ == "__main__":
    main()
