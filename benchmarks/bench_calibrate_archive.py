"""Calibration of long sessions: time and peak memory, side by side in one run (issue 12).

For each size (default 10^3, 10^4, 10^5 frames; ``--sizes`` up to 10^6) one session of 10-30 stars per frame
(seed 004's camera, 0.05 px isotropic centroid noise, no misidentification) is generated chunk by chunk (each
chunk its own seed, so no process ever holds the whole session unless it asks to) and spooled to disk as
calibration data (:func:`hostlink.calibration.data.save_chunk`). Then, each in its own process (peak resident
memory from the kernel's rusage of that process, loading of the input included; one BLAS thread each):

- ``archive``: what ``hostlink calibrate SESSION.parquet`` runs (``hostlink.calibration.run.calibrate_archive``) on
  the same stars written as a Parquet session (reference directions in ra_deg/dec_deg, times 0.1 s apart): the
  session read in chunks of 10^4 frames, reference directions, spooling, then ``chunked``'s fit.
- ``chunked``: ``hostlink.calibration.run.calibrate_chunks`` over the spooled chunks (10^4 frames each): pre-pass,
  voting, robust bundle, held parameters, statistics; memory O(K^2 + one chunk). The baseline of the ratios.
- ``in-memory``: ``hostlink.calibration.run.calibrate`` on the whole session loaded into memory (the same code on
  one chunk).
- ``scipy``: ``scipy.optimize.least_squares`` (trf, sparse finite-difference Jacobian through ``jac_sparsity``:
  each residual depends on the 10 camera parameters and its frame's 3 attitude parameters) on the same residual
  function (``bundle.observation_terms``), plain least squares, from the nominal camera and least-squares (Markley)
  attitudes.
- ``opencv``: the bundle adjustment an engineer would write on OpenCV: its camera model (fx = fy, cx, cy,
  k1, k2, p1, p2, k3), ``cv2.projectPoints`` for the projections and their Jacobians (every star rotated by its
  frame's attitude and projected with rvec = 0, so d/drvec is the derivative by a rotation increment), and
  Levenberg-Marquardt on the sparse normal equations (camera + 3 attitude parameters per frame, scipy's sparse LU),
  from the same start.

Each method's time includes its own imports (OpenCV and scipy ~130 ms, ours ~7 ms), with every package
byte-compiled first (:func:`byte_compile_project`), as installed packages are.

Accuracy: the validation residual (``hostlink.calibration.crb``: RMS over a grid of the detector of the difference
between the estimated and the true camera's directions, best rotation removed) against its Cramer-Rao bound from
the Fisher information of the noise-free session (summed chunk by chunk). Ratios are against ``chunked`` in the same
run, of CPU time (each method single-threaded; the wall time of one run on a shared machine varies several-fold with
the load, its CPU time far less); wall time is printed beside it. Acceptance (issue 12): 10^6 frames chunked under
500 MB and within 1.2x of 10x the 10^5 time; chunked within 0.01 sigma of in-memory at 10^5; >= 5x faster than
OpenCV at 10^4 and 10^5, no slower at 10^3.

Usage: nice -n 10 .venv/bin/python benchmarks/bench_calibrate_archive.py [--sizes 1000,10000,100000]
       [--methods archive,chunked,in-memory,scipy,opencv] [--skip-scipy-above 1000] [--repeat N] [--work DIR]
       [--session N]
With ``--repeat N`` every method runs N times, interleaved, each in a fresh process, and its run of least CPU
time counts for every method alike (timeit's rule: the least disturbed run; at 10^4 frames one run of ours, ~0.6 s,
varies by up to 40 % on a shared machine); the peak memory is the largest of the N.
Results of every size run in a work directory are kept in DIR/results.json (the 10^6 check uses the 10^5 run).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hostlink import api
from hostlink.api import synthetic_session
from hostlink.calibration.bundle import (
    ChunkSource,
    initial_attitudes,
    observation_terms,
    parameter_columns,
    parameter_scales,
)
from hostlink.calibration.data import (
    SPOOL_SUFFIX,
    CalibrationData,
    build_data,
    chunk_frame_count,
    concatenate_data,
    load_chunk,
    save_chunk,
)
from hostlink.calibration.frames import apply_attitude_increment, rotation_from_vector
from hostlink.files.params import load_params
from hostlink.files.session import Session, SessionWriter
from onboard.camera import unit_to_radec
from onboard.params import ESTIMATE_NAMES

TRUTH = load_params("builtin:seed004_camera")
NOMINAL = load_params("builtin:seed004_nominal")
NOISE_PX = 0.05
CHUNK_FRAMES = 10_000
ALL = parameter_columns(ESTIMATE_NAMES)
METHODS = ("archive", "chunked", "in-memory", "scipy", "opencv")
T0 = np.datetime64("2026-03-14T02:00:00.000", "ms")
FRAME_INTERVAL_MS = 100


# ---------------------------------------------------------------------------------------------------- the data
def session_of(d: CalibrationData, first_frame: int) -> Session:
    """The stars of ``d`` as session rows: frames numbered from ``first_frame``, 0.1 s apart, reference directions
    in ra_deg/dec_deg (as ``benchmarks/bench_archive.py`` writes them)."""
    frame = d.frame_index().astype(np.int64) + first_frame
    when = T0 + (frame * FRAME_INTERVAL_MS).astype("timedelta64[ms]")
    ra_rad, dec_rad = unit_to_radec(d.r)
    return Session(
        frame=frame,
        t_utc=np.char.add(np.datetime_as_string(when, unit="ms"), "Z").astype(object),
        star_id=np.arange(1, d.n_obs + 1, dtype=np.int64),
        x_px=d.x_px,
        y_px=d.y_px,
        ra_deg=np.degrees(ra_rad) % 360.0,
        dec_deg=np.degrees(dec_rad),
    )


def generate(frames: int, folder: Path, session: int = 0) -> None:
    """Spool a session of ``frames`` frames to ``folder`` (chunks of CHUNK_FRAMES), the same stars as a Parquet
    session (``session.parquet``, through the one session writer), and its Fisher information. ``session``: which of
    the generator's sessions of that size (each its own seeds; 0 the default one)."""
    folder.mkdir(parents=True, exist_ok=True)
    if (folder / "info.npy").exists() and chunk_files(folder):
        return
    info = np.zeros((10, 10))
    offset = 0
    with SessionWriter(folder / "session.parquet") as writer:
        for k, start in enumerate(range(0, frames, CHUNK_FRAMES)):
            n = min(CHUNK_FRAMES, frames - start)
            ss = synthetic_session(TRUTH, n, noise_px=NOISE_PX, seed=1000 * frames + k + 10**10 * session)
            d = ss.data
            rows = np.arange(d.n_obs, dtype=np.int64) + offset
            offset += d.n_obs
            data = build_data(d.x_px, d.y_px, d.r, d.frame_index(), None, None, rows)
            save_chunk(folder / f"chunk{k:05d}{SPOOL_SUFFIX}", data)
            writer.append(session_of(d, start))
            noise_free = build_data(ss.x_true_px, ss.y_true_px, d.r, d.frame_index())
            info += api.fisher_information(noise_free, TRUTH.model_vector(), ss.attitudes_true, ALL, NOISE_PX)
    np.save(folder / "info.npy", info)


def chunk_files(folder: Path) -> tuple[str, ...]:
    return tuple(str(p) for p in sorted(folder.glob(f"chunk*{SPOOL_SUFFIX}")))


def load_all(folder: Path) -> CalibrationData:
    return concatenate_data([load_chunk(p) for p in chunk_files(folder)])


# ------------------------------------------------------------------------------------------------- the methods
def run_archive(folder: Path) -> np.ndarray:
    from hostlink.calibration.run import calibrate_archive

    return calibrate_archive(str(folder / "session.parquet"), NOMINAL, CHUNK_FRAMES, spool_dir=folder)[0].theta


def run_chunked(folder: Path) -> np.ndarray:
    from hostlink.calibration.run import calibrate_chunks

    return calibrate_chunks(ChunkSource(chunk_files(folder), load_chunk, chunk_frame_count), NOMINAL).theta


def run_in_memory(folder: Path) -> np.ndarray:
    from hostlink.calibration.run import calibrate

    return calibrate(load_all(folder), NOMINAL).theta


def run_scipy(folder: Path) -> np.ndarray:
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    data = load_all(folder)
    scale = parameter_scales(NOMINAL)
    theta0 = NOMINAL.model_vector()
    att0 = initial_attitudes(data, theta0)
    m = data.n_frames
    fidx = data.frame_index()

    def fun(z):
        theta = theta0 + z[:10] * scale
        att = apply_attitude_increment(att0, z[10:].reshape(m, 3))
        e = observation_terms(data.x_px, data.y_px, data.r, att[fidx], theta, np.zeros(0, np.int64))[0]
        return e.ravel()

    n_res = 2 * data.n_obs
    res_rows = np.arange(n_res)
    cam_r = np.repeat(res_rows, 10)
    cam_c = np.tile(np.arange(10), n_res)
    att_r = np.repeat(res_rows, 3)
    att_c = (10 + 3 * np.repeat(fidx, 2)[:, None] + np.arange(3)[None, :]).ravel()
    rows = np.concatenate([cam_r, att_r])
    cols = np.concatenate([cam_c, att_c])
    sparsity = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n_res, 10 + 3 * m)).tocsr()
    sol = least_squares(fun, np.zeros(10 + 3 * m), jac_sparsity=sparsity, method="trf", x_scale="jac", max_nfev=100)
    return theta0 + sol.x[:10] * scale


def _opencv_model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV camera matrix and distortion (k1, k2, p1, p2, k3) from the 8 estimated values (f, cx, cy, k1, k2,
    p1, p2, k3)."""
    cam = np.array([[x[0], 0.0, x[1]], [0.0, x[0], x[2]], [0.0, 0.0, 1.0]])
    return cam, np.array(x[3:8])


def run_opencv(folder: Path, max_iter: int = 100) -> np.ndarray:
    """Levenberg-Marquardt bundle on OpenCV's model and Jacobians; returns the 8 OpenCV values."""
    import cv2
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import spsolve

    data = load_all(folder)
    theta0 = NOMINAL.model_vector()
    fidx = data.frame_index()
    m, n = data.n_frames, data.n_obs
    att = initial_attitudes(data, theta0)
    x = np.array([theta0[0], theta0[1], theta0[2], 0.0, 0.0, 0.0, 0.0, 0.0])
    measured = np.stack([data.x_px, data.y_px], axis=1)
    zero = np.zeros(3)

    def evaluate(x, att, jac: bool):
        cam, dist = _opencv_model(x)
        s = np.einsum("nij,nj->ni", att[fidx], data.r)
        p, j = cv2.projectPoints(s.reshape(-1, 1, 3), zero, zero, cam, dist)
        e = (p.reshape(-1, 2) - measured).ravel()
        if not jac:
            return e, None
        # columns of j: rvec(3), tvec(3), fx, fy, cx, cy, k1, k2, p1, p2, k3
        j_cam = np.concatenate([j[:, 6:7] + j[:, 7:8], j[:, 8:10], j[:, 10:15]], axis=1)
        return e, (j_cam, j[:, 0:3])

    e, jacs = evaluate(x, att, True)
    cost = float(e @ e)
    lam = 1e-3
    res_rows = np.arange(2 * n)
    frame_of_res = np.repeat(fidx, 2)
    for _ in range(max_iter):
        j_cam, j_att = jacs
        rows = np.concatenate([np.repeat(res_rows, 8), np.repeat(res_rows, 3)])
        cols = np.concatenate(
            [np.tile(np.arange(8), 2 * n), (8 + 3 * frame_of_res[:, None] + np.arange(3)[None, :]).ravel()]
        )
        jac = coo_matrix((np.concatenate([j_cam.ravel(), j_att.ravel()]), (rows, cols)), shape=(2 * n, 8 + 3 * m))
        jac = jac.tocsr()
        jtj = (jac.T @ jac).tocsc()
        g = jac.T @ e
        improved = False
        for _trial in range(10):
            step = spsolve(jtj + diags(lam * jtj.diagonal()), -g)
            x_new = x + step[:8]
            att_new = rotation_from_vector(step[8:].reshape(m, 3)) @ att
            e_new, _ = evaluate(x_new, att_new, False)
            cost_new = float(e_new @ e_new)
            if cost_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        decrease = (cost - cost_new) / cost
        x, att, cost = x_new, att_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        e, jacs = evaluate(x, att, True)
        if decrease < 1e-10:
            break
    return x


RUNNERS = {
    "archive": run_archive,
    "chunked": run_chunked,
    "in-memory": run_in_memory,
    "scipy": run_scipy,
    "opencv": run_opencv,
}


# ------------------------------------------------------------------------------------------------ the accuracy
def validation_px(method: str, estimate: np.ndarray) -> float:
    """Validation residual [px] of an estimate: our model vector, or OpenCV's 8 values (directions of the grid
    through cv2.undistortPoints, aligned to the truth's by the best rotation, as for ours)."""
    if method != "opencv":
        return api.validation_residual_px(estimate, TRUTH)
    import cv2

    gx, gy = api.grid_points(TRUTH)
    cam, dist = _opencv_model(estimate)
    und = cv2.undistortPoints(np.stack([gx, gy], axis=1).reshape(-1, 1, 2), cam, dist, criteria=None)
    und = und.reshape(-1, 2)
    b_est = np.concatenate([und, np.ones((und.shape[0], 1))], axis=1)
    b_est /= np.linalg.norm(b_est, axis=1, keepdims=True)
    return api.validation_residual_from_directions_px(b_est, TRUTH)


# ----------------------------------------------------------------------------------------------- the harness
def child(method: str, folder: Path) -> None:
    """Run one method in this process and print its result as one JSON line."""
    t0, cpu0 = time.perf_counter(), time.process_time()
    estimate = RUNNERS[method](folder)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    out = {"time_s": elapsed, "cpu_s": cpu, "estimate": [float(v) for v in estimate], "vmhwm_mb": _vmhwm_mb()}
    print(json.dumps(out))


def _vmhwm_mb() -> float:
    """This process's own high-water resident memory [MB] (VmHWM, Linux): a cross-check of the parent's
    ``ru_maxrss`` of the child; NaN where /proc is absent."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


#: Started by the harness, starts the measured child and reports the child's rusage. A process started by another
#: inherits the starter's resident size as the floor of its ``ru_maxrss`` (Linux records the old image's high-water
#: mark at exec), so the starter is this small interpreter (~10 MB), not the harness with numpy and the Fisher sums.
LAUNCHER = """
import json, os, sys
pid = os.posix_spawn(sys.argv[1], sys.argv[1:], os.environ)
_, status, usage = os.wait4(pid, 0)
print(json.dumps({"child_maxrss_kb": usage.ru_maxrss}), flush=True)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def run_measured(method: str, folder: Path) -> dict:
    """Run ``child`` in a fresh process; its peak resident memory [MB] from the kernel's rusage of that process
    (``wait4`` in :data:`LAUNCHER`)."""
    cmd = [sys.executable, "-c", LAUNCHER, sys.executable, __file__, "--child", method, "--work", str(folder)]
    # one BLAS thread for every method: the same footing, and no oversubscription of a shared machine
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        err = proc.stderr.strip()
        return {"error": err.splitlines()[-1] if err else f"exit {proc.returncode}"}
    lines = proc.stdout.strip().splitlines()
    result = json.loads(lines[-2])
    result["peak_mb"] = json.loads(lines[-1])["child_maxrss_kb"] / 1024.0
    return result


def byte_compile_project() -> None:
    """Byte-compile the project's packages, as an installed package is (pip compiles at install; an editable install
    under PYTHONDONTWRITEBYTECODE never caches its bytecode), so no method's timed import compiles source: OpenCV's
    and scipy's modules come compiled from their wheels, and ours would otherwise cost ~15 ms more to import."""
    import compileall

    root = Path(__file__).resolve().parents[1]
    for package in ("hostlink", "onboard", "protocol"):
        compileall.compile_dir(root / package, quiet=1)


def _prepare(frames: int, folder: Path, session: int) -> tuple[float, np.ndarray]:
    """The session of ``frames`` frames generated into ``folder`` (unless there already), and from its Fisher
    information the Cramer-Rao bound of the validation residual [px] and each parameter's CRB sigma (printed)."""
    t0 = time.perf_counter()
    generate(frames, folder, session)
    info = np.load(folder / "info.npy")
    bound = api.crb_validation_px(info, api.validation_jacobian(TRUTH, ALL))
    d = np.sqrt(np.diag(info))  # equilibrated: the entries span 30 orders of magnitude
    sigma = np.sqrt(np.diag(np.linalg.pinv(info / d[:, None] / d[None, :], hermitian=True))) / d
    print(
        f"\n{frames} frames (data ready in {time.perf_counter() - t0:.1f} s); CRB of the validation residual "
        f"{bound:.5f} px",
        flush=True,
    )
    return bound, sigma


def _scored(methods: list[str], runs: dict[str, list[dict]], bound: float, skip_scipy_above: int) -> dict:
    """Each method's best run (:func:`_best_run`) with its validation residual against the bound ``bound`` [px],
    each printed (a method without runs: skipped)."""
    results = {}
    for method in methods:
        if method not in runs:
            print(f"  {method:10s} skipped (above {skip_scipy_above} frames)", flush=True)
            continue
        r = _best_run(runs[method])
        results[method] = r
        if "error" in r:
            print(f"  {method:10s} FAILED: {r['error']}", flush=True)
            continue
        v = validation_px(method, np.array(r["estimate"]))
        r["validation_px"] = v
        r["crb_px"] = bound
        cpu_runs = r["cpu_runs_s"]
        spread = f" (best of {len(cpu_runs)}; the slowest {max(cpu_runs):.2f} s CPU)" if len(cpu_runs) > 1 else ""
        print(
            f"  {method:10s} {r['time_s']:9.2f} s wall {r['cpu_s']:9.2f} s CPU  peak {r['peak_mb']:8.1f} MB "
            f"(own VmHWM {r['vmhwm_mb']:.1f})  "
            f"validation {v:.5f} px ({v / bound:.2f}x CRB){spread}",
            flush=True,
        )
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1000,10000,100000")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--skip-scipy-above", type=int, default=1000, help="scipy takes minutes past this")
    ap.add_argument("--work", default="/tmp/hostlink-bench-archive")
    ap.add_argument(
        "--session",
        type=int,
        default=0,
        help="another session of each size (its own seeds, in WORK-sN): the fit's passes over the data, and so its "
        "time, vary from one session to another",
    )
    ap.add_argument(
        "--repeat", type=int, default=1, help="runs of each method (fresh processes); the one of least CPU time counts"
    )
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, Path(args.work))
        return
    work = Path(args.work) if args.session == 0 else Path(f"{args.work}-s{args.session}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    byte_compile_project()
    sigma_of = {}
    results: dict[int, dict[str, dict]] = {}
    for frames in [int(s) for s in args.sizes.split(",")]:
        folder = work / f"frames{frames}"
        bound, sigma_of[frames] = _prepare(frames, folder, args.session)
        runs: dict[str, list[dict]] = {}
        for _ in range(args.repeat):  # interleaved: every method sees the same spells of a shared machine's load
            for method in methods:
                if not (method == "scipy" and frames > args.skip_scipy_above):
                    runs.setdefault(method, []).append(run_measured(method, folder))
        results[frames] = _scored(methods, runs, bound, args.skip_scipy_above)
        _compare(results[frames], sigma_of[frames])
    store = work / "results.json"  # every size ever run here, the latest run of each (the scaling check below)
    saved = json.loads(store.read_text()) if store.exists() else {}
    saved.update({str(k): v for k, v in results.items()})
    store.write_text(json.dumps(saved, indent=1))
    _scaling({int(k): v for k, v in saved.items()})


def _best_run(runs: list[dict]) -> dict:
    """Of one method's runs, the one of least CPU time (the timing least disturbed by other work on the machine:
    the estimate is the same in every run), with every run's CPU time and the largest peak memory of them all;
    the first failure when a run failed."""
    failed = [r for r in runs if "error" in r]
    if failed:
        return failed[0]
    best = dict(min(runs, key=lambda r: r["cpu_s"]))
    best["cpu_runs_s"] = [r["cpu_s"] for r in runs]
    best["peak_mb"] = max(r["peak_mb"] for r in runs)
    best["vmhwm_mb"] = max(r["vmhwm_mb"] for r in runs)
    return best


def _ok(r: dict | None) -> bool:
    return bool(r) and "error" not in r


def _compare(res: dict[str, dict], sigma: np.ndarray) -> None:
    """CPU-time ratios against ``chunked`` (and OpenCV's against ours), and ours against the in-memory estimate.
    CPU time of the method in its process (every method single-threaded): on a machine shared with other work the
    wall time of one run varies several-fold with the load, the CPU time much less."""
    base = res.get("chunked")
    if not _ok(base):
        return
    for method, r in res.items():
        if method not in ("chunked", "opencv") and _ok(r):
            print(f"  {method} / chunked CPU time: {r['cpu_s'] / base['cpu_s']:.2f}x")
    for ours in ("chunked", "archive"):
        if _ok(res.get("opencv")) and _ok(res.get(ours)):
            ratio = res["opencv"]["cpu_s"] / res[ours]["cpu_s"]
            print(f"  opencv / {ours} CPU time: {ratio:.2f}x (acceptance >= 5)")
        if _ok(res.get("in-memory")) and _ok(res.get(ours)):
            d = np.abs(np.array(res[ours]["estimate"]) - np.array(res["in-memory"]["estimate"]))[ALL] / sigma
            print(f"  {ours} vs in-memory: largest difference {d.max():.2e} sigma (CRB sigma; acceptance < 0.01)")


def _scaling(saved: dict[int, dict[str, dict]]) -> None:
    """Each size's time of ours against the next smaller size's times the frame ratio (acceptance at 10^6:
    within 1.2 x of 10 x the 10^5 time), and the peak memory (acceptance at 10^6: under 500 MB)."""
    sizes = sorted(saved)
    for ours in ("chunked", "archive"):
        for small, big in zip(sizes[:-1], sizes[1:], strict=True):
            a, b = saved[small].get(ours), saved[big].get(ours)
            if _ok(a) and _ok(b):
                ratio = b["time_s"] / (a["time_s"] * big / small)
                ratio_cpu = b["cpu_s"] / (a["cpu_s"] * big / small)
                print(
                    f"{ours} {big} frames: {b['time_s']:.1f} s wall = {ratio:.2f} x ({big // small} x the "
                    f"{small}-frame time), CPU {b['cpu_s']:.1f} s = {ratio_cpu:.2f} x; peak {b['peak_mb']:.0f} MB"
                )


if __name__ == "__main__":
    main()
