"""Benchmark of the default calibration (bundle adjustment with the Schur complement), run on demand.

1. Speed, side by side in one run: 1000 frames of 10-30 stars (seed 004's camera, 0.05 px noise). The same plain
   least-squares bundle problem (same residual function ``bundle.observation_terms``, same start: nominal camera and
   per-frame least-squares (Markley) attitudes; the default method's robust loss, gating and screening switched off
   so that both solve exactly the same problem) is solved by ``hostlink.calibration.bundle.bundle_adjust`` and by
   ``scipy.optimize.least_squares`` (trf, finite-difference Jacobian with ``jac_sparsity``: each residual depends
   on the 10 camera parameters and its frame's 3 attitude parameters). scipy runs twice: with its default
   tolerances, and with tight ones (1e-15) so that it may reach the same optimum. Speed is compared at equal
   quality: the time each needs to reach a given sum of squares. Prints times, sums of squares and validation
   residuals, and the ratios.
2. Memory (``--memory-frames N``): peak traced memory (tracemalloc) of ``bundle_adjust`` on N frames, next to the
   size of its input arrays, and the same at N/10 frames: bounded working memory means the peak grows like the
   input (linear in frames) with no term in frames^2 (no dense Jacobian, no full normal matrix).
3. Methods side by side (``--methods all`` or a comma list of ``hostlink.calibration.run.METHODS``): the full
   ``run.calibrate`` of each method (voting, fit, gating, statistics) on the same sessions of 1000 and 10000
   frames (``--method-frames``), with its time, time per 1000 frames, iterations and validation residual. Time
   linear in frames shows as a constant time per 1000 frames.

Usage: .venv/bin/python benchmarks/bench_calibrate.py [--frames 1000] [--memory-frames 100000]
       .venv/bin/python benchmarks/bench_calibrate.py --methods all [--method-frames 1000,10000]
"""

from __future__ import annotations

import argparse
import time
import tracemalloc
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from hostlink.api import synthetic_session, validation_residual_px
from hostlink.calibration.bundle import (
    BundleOptions,
    bundle_adjust,
    initial_attitudes,
    observation_terms,
    parameter_scales,
)
from hostlink.calibration.frames import apply_attitude_increment
from hostlink.files.params import load_params

TRUTH = load_params("builtin:seed004_camera")
NOMINAL = load_params("builtin:seed004_nominal")


def scipy_bundle(data, nominal, max_nfev: int = 100, tol: float | None = None):
    """The same problem through scipy.optimize.least_squares with a finite-difference sparse Jacobian.
    Returns (theta, sum of squares, evaluations, status)."""
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
    tols = {} if tol is None else {"ftol": tol, "xtol": tol, "gtol": tol}
    sol = least_squares(
        fun, np.zeros(10 + 3 * m), jac_sparsity=sparsity, method="trf", x_scale="jac", max_nfev=max_nfev, **tols
    )
    return theta0 + sol.x[:10] * scale, float(np.sum(sol.fun**2)), sol.nfev, sol.status


#: The default method's options, with the robust loss, outlier gating and screening off: plain least squares.
PLAIN_LS = BundleOptions(huber_k=1e12, gate=1e12)


def ours(data, max_iter: int):
    t0 = time.perf_counter()
    res = bundle_adjust(data, NOMINAL, replace(PLAIN_LS, max_iter=max_iter), screen=False)
    elapsed = time.perf_counter() - t0
    e = res_residuals(data, res)
    return res, float(np.sum(e * e)), elapsed


def res_residuals(data, res):
    from hostlink.calibration.bundle import residuals

    return residuals(res.data, res.theta, res.attitudes)


def ours_time_to_reach(data, target_ssq: float, max_iter: int):
    """Time of the shortest run of ours (capped at k iterations, k = 1, 2, ...) whose sum of squares <= target."""
    for k in range(1, max_iter + 1):
        res, ssq, elapsed = ours(data, k)
        if ssq <= target_ssq:
            return elapsed, k, ssq
    return float("nan"), max_iter, ssq


def speed(frames: int) -> None:
    ss = synthetic_session(TRUTH, frames, stars_per_frame=(10, 30), noise_px=0.05, seed=1)
    d = ss.data
    print(
        f"speed: {frames} frames, {d.n_obs} stars, 10 camera parameters + {3 * frames} attitude parameters", flush=True
    )
    res, ssq_ours, t_ours = ours(d, 100)
    t0 = time.perf_counter()
    theta_sp, ssq_sp, nfev, status = scipy_bundle(d, NOMINAL)
    t_scipy = time.perf_counter() - t0
    t0 = time.perf_counter()
    theta_tight, ssq_tight, nfev_tight, status_tight = scipy_bundle(d, NOMINAL, max_nfev=60, tol=1e-15)
    t_tight = time.perf_counter() - t0
    t_equal, k_equal, _ = ours_time_to_reach(d, ssq_sp, 100)
    rows = [
        ("ours (Schur, chunked), to convergence", t_ours, ssq_ours, f"{len(res.history)} iterations", res.theta),
        ("scipy, default tolerances", t_scipy, ssq_sp, f"{nfev} evaluations, status {status}", theta_sp),
        (
            "scipy, tolerances 1e-15",
            t_tight,
            ssq_tight,
            f"{nfev_tight} evaluations, status {status_tight}",
            theta_tight,
        ),
    ]
    for name, t, ssq, what, theta in rows:
        print(
            f"  {name:40s} {t:8.3f} s  sum of squares {ssq:.9f}  validation residual "
            f"{validation_residual_px(theta, TRUTH):.5f} px  ({what})",
            flush=True,
        )
    print(
        f"  ours reaches scipy's default answer (sum of squares <= {ssq_sp:.9f}) in {t_equal:.3f} s "
        f"({k_equal} iterations)"
    )
    print(
        f"  speed ratio at scipy's default answer: {t_scipy / t_equal:.1f}x  (scipy {t_scipy:.2f} s / ours "
        f"{t_equal:.3f} s)"
    )
    if ssq_tight > ssq_ours * (1 + 1e-9):
        print(
            f"  scipy with tight tolerances stopped above our optimum after {t_tight:.1f} s: at our answer the "
            f"ratio is more than {t_tight / t_ours:.0f}x"
        )
    else:
        print(f"  speed ratio at the common optimum: {t_tight / t_ours:.1f}x")
    print(f"  speed ratio, each to its own stopping rule (scipy stops before the optimum): {t_scipy / t_ours:.1f}x")


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
        print(
            f"memory: {n} frames, {d.n_obs} stars: peak {peak / 1e6:.1f} MB traced "
            f"({peak / input_bytes:.1f}x the {input_bytes / 1e6:.1f} MB input), {elapsed:.1f} s, "
            f"{len(res.history)} iterations, validation residual {validation_residual_px(res.theta, TRUTH):.5f} px"
        )


def interstar_pass(data, form: str) -> tuple[float, int]:
    """Time [s] and peak traced memory [bytes] of one pass of the seed methods' normal equations
    (``interstar_methods.interstar_normals``) at the nominal camera; the pair orders are computed outside it."""
    from hostlink.calibration.bundle import parameter_columns
    from hostlink.calibration.interstar_methods import frame_pair_orders, interstar_normals
    from onboard.params import ESTIMATE_NAMES

    cols = parameter_columns(ESTIMATE_NAMES)
    orders = frame_pair_orders(data)
    args = (data, NOMINAL.model_vector(np.float64), cols, form, orders, parameter_scales(NOMINAL)[cols])
    t0 = time.perf_counter()
    interstar_normals(*args)
    elapsed = time.perf_counter() - t0
    tracemalloc.start()
    interstar_normals(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return elapsed, peak


def methods_side_by_side(methods: list[str], frame_counts: list[int]) -> None:
    """Every method's full calibration (``run.calibrate``) on the same sessions, timed one after the other."""
    from hostlink.calibration.run import calibrate

    for n in frame_counts:
        ss = synthetic_session(TRUTH, n, stars_per_frame=(10, 30), noise_px=0.05, seed=3)
        print(f"methods: {n} frames, {ss.data.n_obs} stars", flush=True)
        for form in ("cos", "sin"):
            elapsed, peak = interstar_pass(ss.data, form)
            print(
                f"  one interstar normal-equation pass ({form}, 10 parameters): {1000 * elapsed / n * 1000:7.1f} ms "
                f"per 1000 frames, peak {peak / 1e6:.1f} MB traced",
                flush=True,
            )
        for method in methods:
            t0 = time.perf_counter()
            out = calibrate(ss.data, NOMINAL, method)
            elapsed = time.perf_counter() - t0
            print(
                f"  {method:16s} {elapsed:9.2f} s  {1000 * elapsed / n:7.3f} s per 1000 frames  "
                f"{len(out.history):3d} iterations  validation residual "
                f"{validation_residual_px(out.theta, TRUTH):.5f} px",
                flush=True,
            )


def main() -> None:
    from hostlink.calibration.run import METHODS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--memory-frames", type=int, default=0, help="also run the memory check on N frames")
    parser.add_argument(
        "--methods",
        default="",
        help="'all' or a comma list of calibration methods: time each "
        "method side by side instead of the scipy comparison",
    )
    parser.add_argument("--method-frames", default="1000,10000", help="comma list of session sizes for --methods")
    args = parser.parse_args()
    if args.methods:
        methods = list(METHODS) if args.methods == "all" else [m.strip() for m in args.methods.split(",")]
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            parser.error(f"unknown method(s) {', '.join(unknown)} (choose from {', '.join(METHODS)})")
        try:
            counts = [int(v) for v in args.method_frames.split(",")]
        except ValueError:
            parser.error(f"--method-frames: expected a comma list of integers, got {args.method_frames!r}")
        methods_side_by_side(methods, counts)
        return
    speed(args.frames)
    if args.memory_frames:
        memory(args.memory_frames)


if __name__ == "__main__":
    main()
