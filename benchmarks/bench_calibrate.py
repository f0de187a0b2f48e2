"""Benchmark of the default calibration (bundle adjustment with the Schur complement), run on demand.

1. Speed, side by side in one run: 1000 frames of 10-30 stars (seed 004's camera, 0.05 px noise). The same bundle
   problem (same residual function ``bundle.observation_terms``, same start: nominal camera and per-frame SVD
   attitudes) is solved by ``hostlink.calibration.bundle.bundle_adjust`` and by
   ``scipy.optimize.least_squares`` (trf, finite-difference Jacobian with ``jac_sparsity``: each residual depends
   on the 10 camera parameters and its frame's 3 attitude parameters). Prints both times, the speed ratio and both
   solutions' validation residual (they must agree: same optimum).
2. Memory (``--memory-frames N``): peak traced memory (tracemalloc) of ``bundle_adjust`` on N frames, next to the
   size of its input arrays, and the same at N/10 frames: bounded working memory means the peak grows like the
   input (linear in frames) with no term in frames^2 (no dense Jacobian, no full normal matrix).

Usage: .venv/bin/python benchmarks/bench_calibrate.py [--frames 1000] [--memory-frames 100000]
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from hostlink.calibration.bundle import (
    BundleOptions,
    bundle_adjust,
    initial_attitudes,
    observation_terms,
    parameter_scales,
)
from hostlink.calibration.crb import validation_residual_px
from hostlink.calibration.frames import apply_attitude_increment
from hostlink.calibration.synthetic import synthetic_session
from onboard.params import CameraParams, distortion_from_seed004

TRUTH = CameraParams(70.2262, 12.0, (500.0, 530.0), (1024, 1024), distortion_from_seed004(2e-10, -3.5e-15))
NOMINAL = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))


def scipy_bundle(data, nominal, max_nfev: int = 100):
    """The same problem through scipy.optimize.least_squares with a finite-difference sparse Jacobian."""
    scale = parameter_scales(nominal)
    theta0 = nominal.model_vector()
    att0 = initial_attitudes(data, theta0)
    m = data.n_frames
    att_obs_index = data.frame_index()

    def fun(z):
        theta = theta0 + z[:10] * scale
        att = apply_attitude_increment(att0, z[10:].reshape(m, 3))
        e = observation_terms(data.x_px, data.y_px, data.r, att[att_obs_index], theta, np.zeros(0, np.int64))[0]
        return e.ravel()

    sparsity = lil_matrix((2 * data.n_obs, 10 + 3 * m), dtype=int)
    sparsity[:, :10] = 1
    rows = np.arange(2 * data.n_obs)
    frame_of_row = np.repeat(att_obs_index, 2)
    for a in range(3):
        sparsity[rows, 10 + 3 * frame_of_row + a] = 1
    # scipy's default tolerances (1e-8): tighter ones only add iterations of LSMR without changing the optimum
    # at the reported precision; max_nfev caps a run that would otherwise take hours
    sol = least_squares(fun, np.zeros(10 + 3 * m), jac_sparsity=sparsity, method="trf", x_scale="jac",
                        max_nfev=max_nfev)
    return theta0 + sol.x[:10] * scale, sol.nfev, sol.status


def speed(frames: int) -> None:
    ss = synthetic_session(TRUTH, frames, stars_per_frame=(10, 30), noise_px=0.05, seed=1)
    print(f"speed: {frames} frames, {ss.data.n_obs} stars, 10 camera parameters + {3 * frames} attitude parameters",
          flush=True)
    t0 = time.perf_counter()
    res = bundle_adjust(ss.data, NOMINAL, BundleOptions())
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    theta_sp, nfev, status = scipy_bundle(ss.data, NOMINAL)
    t_scipy = time.perf_counter() - t0
    v_ours = validation_residual_px(res.theta, TRUTH)
    v_sp = validation_residual_px(theta_sp, TRUTH)
    print(f"  bundle_adjust (Schur, chunked):          {t_ours:8.3f} s, {len(res.history)} iterations, "
          f"validation residual {v_ours:.5f} px", flush=True)
    print(f"  scipy least_squares (FD, jac_sparsity):  {t_scipy:8.3f} s, {nfev} evaluations, "
          f"validation residual {v_sp:.5f} px ({'converged' if status > 0 else 'stopped at max_nfev'})", flush=True)
    print(f"  speed ratio scipy / ours: {t_scipy / t_ours:.1f}x")


def memory(frames: int) -> None:
    for n in (max(frames // 10, 1), frames):
        ss = synthetic_session(TRUTH, n, stars_per_frame=(10, 30), noise_px=0.05, seed=2)
        d = ss.data
        input_bytes = d.x_px.nbytes + d.y_px.nbytes + d.r.nbytes + d.star_id.nbytes + d.frame_starts.nbytes
        tracemalloc.start()
        t0 = time.perf_counter()
        res = bundle_adjust(d, NOMINAL, BundleOptions())
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"memory: {n} frames, {d.n_obs} stars: peak {peak / 1e6:.1f} MB traced "
              f"({peak / input_bytes:.1f}x the {input_bytes / 1e6:.1f} MB input), {elapsed:.1f} s, "
              f"{len(res.history)} iterations, validation residual {validation_residual_px(res.theta, TRUTH):.5f} px")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--memory-frames", type=int, default=0, help="also run the memory check on N frames")
    args = parser.parse_args()
    speed(args.frames)
    if args.memory_frames:
        memory(args.memory_frames)


if __name__ == "__main__":
    main()
