"""Benchmark (not a test) of the real-sky simulator: seed 004's setup (10-30 stars a frame) at 250, 500, 1000 and
2000 frames, measured side by side in one run. Prints the seconds (best of --repeat), the cost per frame, and each
per-frame cost as a ratio to the 1000-frame one: linear cost means ratios near 1 (the small fixed cost of loading the
cached catalogue makes the smallest runs slightly dearer per frame). Also times a cached catalogue load.

    .venv/bin/python benchmarks/bench_simulate.py [--repeat 3] [--frames 250,500,1000,2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hostlink.sky.catalogue import load_catalogue
from hostlink.sky.simulate import seed004_config, simulate


def best_of(repeat: int, fn) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--frames", default="250,500,1000,2000")
    args = parser.parse_args()
    sizes = [int(v) for v in args.frames.split(",")]

    load_catalogue()  # make sure the cache exists
    t_cat = best_of(args.repeat, load_catalogue)
    print(f"cached catalogue load: {t_cat * 1000:.1f} ms")

    rows = {}
    seconds = {}
    for n in sizes:
        cfg = seed004_config(frames=n, seed=1)
        seconds[n] = best_of(args.repeat, lambda cfg=cfg: simulate(cfg))
        rows[n] = len(simulate(cfg).session)
    ref = 1000 if 1000 in seconds else sizes[len(sizes) // 2]
    per_ref = seconds[ref] / ref
    print(f"{'frames':>8} {'stars':>8} {'seconds':>9} {'ms/frame':>9} {'ratio to ' + str(ref):>14}")
    for n in sizes:
        per = seconds[n] / n
        print(f"{n:>8} {rows[n]:>8} {seconds[n]:>9.3f} {per * 1000:>9.3f} {per / per_ref:>14.2f}")
    slope = np.polyfit(np.array(sizes, float), np.array([seconds[n] for n in sizes]), 1)
    print(f"linear fit: {slope[0] * 1000:.3f} ms/frame + {slope[1] * 1000:.1f} ms fixed")


if __name__ == "__main__":
    main()
