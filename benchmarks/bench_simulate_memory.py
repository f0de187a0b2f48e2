"""Benchmark (not a test) of ``hostlink simulate``'s memory: the command run as a user runs it, in a fresh process
per size, its peak resident set (``resource.getrusage(RUSAGE_SELF).ru_maxrss``, read by the child itself as it
exits) printed beside the frames and rows. The simulation streams to disk chunk by
chunk (issue 31), so the peak should not grow with the number of frames; the acceptance is 10^6 frames under
500 MB.

    .venv/bin/python benchmarks/bench_simulate_memory.py [--frames 20000,200000] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: Issue 31's acceptance: ``simulate --frames 1000000`` under this peak [MB].
ACCEPT_PEAK_MB = 500.0

_CHILD = """
import resource, sys
from hostlink.cli import main
code = main(sys.argv[1:])
print("PEAK_MB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, file=sys.stderr)
sys.exit(code)
"""


def run(frames: int, out_dir: Path) -> dict:
    out = out_dir / f"s{frames}.csv"
    args = ["simulate", "--preset", "seed004", "--frames", str(frames), "--misid", "0.03", "--false-stars", "0.1"]
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, *args, "--out", str(out)], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(proc.stderr)
    peak = float(next(line.split()[1] for line in proc.stderr.splitlines() if line.startswith("PEAK_MB")))
    rows = int(proc.stdout.split(" frames, ")[1].split()[0])
    truth = json.loads((out_dir / f"s{frames}.truth.json").read_text())
    assert len(truth["attitude"]) == frames
    size_mb = out.stat().st_size / 1e6
    for p in out_dir.glob(f"s{frames}*"):
        p.unlink()
    return {"frames": frames, "rows": rows, "peak_mb": peak, "seconds": seconds, "csv_mb": size_mb}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="20000,200000")
    parser.add_argument("--out", help="directory for the session files (default: a temporary one)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = Path(args.out or tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        results = [run(int(n), out_dir) for n in args.frames.split(",")]
    first = results[0]
    for r in results:
        verdict = "ok" if r["peak_mb"] < ACCEPT_PEAK_MB else "NOT under"
        print(
            f"{r['frames']:>8} frames {r['rows']:>9} rows  peak {r['peak_mb']:6.0f} MB "
            f"({r['peak_mb'] / first['peak_mb']:.2f} x the {first['frames']}-frame run)  {r['seconds']:6.1f} s  "
            f"CSV {r['csv_mb']:.0f} MB  {verdict} {ACCEPT_PEAK_MB:.0f} MB"
        )


if __name__ == "__main__":
    main()
