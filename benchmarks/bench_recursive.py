"""Benchmark: onboard recursive estimator frames per second (20 identified stars per frame), float32 (the sensor)
and float64 (the host reference) measured side by side in one run. Target (issue 4): >= 500 frames/s in float32 so
that the emulator never limits a bench.

    .venv/bin/python benchmarks/bench_recursive.py [--frames 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hostlink.api import make_frames, seed004_paper_start, seed004_true_camera
from onboard import recursive

SEED004_TRUE = seed004_true_camera()
SEED004_PAPER_START = seed004_paper_start()


def frames_per_second(frames, dtype) -> float:
    state = recursive.create(SEED004_PAPER_START, dtype=dtype)
    for fr in frames[:50]:  # cold start (iterated updates) excluded: steady state is what a bench sees
        recursive.update(state, fr.x_px, fr.y_px, fr.r, fr.identified)
    t0 = time.perf_counter()
    for fr in frames[50:]:
        recursive.update(state, fr.x_px, fr.y_px, fr.r, fr.identified)
    return (len(frames) - 50) / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    frames = make_frames(SEED004_TRUE, args.frames + 50, 0.05, min_stars=20, max_stars=20, seed=1)
    f32 = frames_per_second(frames, np.float32)
    f64 = frames_per_second(frames, np.float64)
    print(f"recursive estimator, 20 stars/frame, {args.frames} frames after a 50-frame cold start")
    verdict = "ok" if f32 >= 500 else "MISSED"
    print(f"  float32: {f32:8.0f} frames/s  ({1e3 / f32:.2f} ms/frame)  target >= 500: {verdict}")
    print(f"  float64: {f64:8.0f} frames/s  ({1e3 / f64:.2f} ms/frame)")
    print(f"  float32 / float64 speed ratio: {f32 / f64:.2f}")


if __name__ == "__main__":
    main()
