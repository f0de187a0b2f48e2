"""Benchmark: the fixed-point front end (onboard/fixedpoint.py) against float32, measured side by side in one run.

Two figures, 20 identified stars per frame (seed-004 camera): the whole recursive estimator in frames/s, float32
against ``fixed`` (integer front end + float32 filter), and the per-frame front end alone (centroids -> unit vectors
-> 37 interstar residuals), float32 camera model against the integer one. numpy on a PC says how the reference model
costs, not how a sensor without an FPU would (there the integer path is the fast one); the ratio is what a bench
run through ``hostlink replay --precision fixed`` sees.

    .venv/bin/python benchmarks/bench_fixedpoint.py [--frames 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from hostlink.api import make_frames, seed004_paper_start, seed004_true_camera
from onboard import fixedpoint, recursive
from onboard.camera import pixels_to_unit
from onboard.interstar import difference_residuals, independent_pairs
from protocol.messages import dequantise_px, quantise_px

SEED004_TRUE = seed004_true_camera()
SEED004_PAPER_START = seed004_paper_start()


def wire_frames(frames):
    """Each frame as the fixed sensor gets it: (x, y dequantised, r, identified, FixedFrame)."""
    out = []
    for fr in frames:
        xs, ys = quantise_px(fr.x_px), quantise_px(fr.y_px)
        front = fixedpoint.FixedFrame(xs, ys, fixedpoint.quantise_unit_q30(fr.r), SEED004_TRUE.image_size_px)
        out.append((dequantise_px(xs), dequantise_px(ys), fr.r, fr.identified, front))
    return out


def estimator_fps(frames, fixed: bool) -> float:
    state = recursive.create(SEED004_PAPER_START, dtype=np.float32)
    for x, y, r, ok, front in frames[:50]:  # cold start excluded, as in bench_recursive.py
        recursive.update(state, x, y, r, ok, front_end=front if fixed else None)
    t0 = time.perf_counter()
    for x, y, r, ok, front in frames[50:]:
        recursive.update(state, x, y, r, ok, front_end=front if fixed else None)
    return (len(frames) - 50) / (time.perf_counter() - t0)


def front_end_fps(frames, fixed: bool) -> float:
    theta32 = SEED004_TRUE.model_vector(np.float32)
    n = frames[0][0].size
    pi, pj = independent_pairs(n)
    rows = np.arange(n)
    t0 = time.perf_counter()
    for x, y, r, _, front in frames:
        if fixed:
            front.residuals(theta32, rows, pi, pj)
        else:
            b = pixels_to_unit(x.astype(np.float32), y.astype(np.float32), theta32)
            difference_residuals(b, r.astype(np.float32), pi, pj)
    return len(frames) / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    frames = wire_frames(make_frames(SEED004_TRUE, args.frames + 50, 0.05, min_stars=20, max_stars=20, seed=1))
    e32, efx = estimator_fps(frames, False), estimator_fps(frames, True)
    f32, ffx = front_end_fps(frames, False), front_end_fps(frames, True)
    print(f"recursive estimator, 20 stars/frame, {args.frames} frames after a 50-frame cold start")
    print(f"  float32: {e32:8.0f} frames/s   fixed: {efx:8.0f} frames/s   fixed / float32: {efx / e32:.2f}")
    print("front end alone (unit vectors + 37 residuals per frame, incl. the fixed camera conversion)")
    print(f"  float32: {f32:8.0f} frames/s   fixed: {ffx:8.0f} frames/s   fixed / float32: {ffx / f32:.2f}")


if __name__ == "__main__":
    main()
