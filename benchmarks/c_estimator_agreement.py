"""Study (on demand): the C firmware core's estimator (onboard/c) against the Python sensor over several simulated
sessions, float32 and fixed: the frames after which their saved states differ (both evaluate the float32 filter in
the order of onboard.linalg32, so none should), how far the C ends from the Python after the session in units of
the Python sensor's 1-sigma (issue 27's acceptance: under 0.01), beside how far the Python float32 sensor ends from
the same code in float64 (float32's own rounding). Also the time per frame of each, measured side by side.

    .venv/bin/python benchmarks/c_estimator_agreement.py [--frames 1000] [--sessions 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_replay_cli import NOMINAL  # noqa: E402

from hostlink.portkit.estimator_c import CEstimator  # noqa: E402
from hostlink.sky.references import session_references  # noqa: E402
from hostlink.sky.simulate import seed004_config, simulate  # noqa: E402
from onboard import firmware, recursive  # noqa: E402
from onboard.params import ESTIMATE_NAMES, params_from_dict  # noqa: E402


def one_session(nominal, n_frames: int, seed: int, precision: str) -> tuple[float, float, float, float, int]:
    """(max |C - Python| / sigma, max |Python64 - Python32| / sigma, Python s/frame, C s/frame) after the session,
    and the number of frames after which the C and Python saved states differ."""
    session = simulate(seed004_config(n_frames, seed=seed)).session
    refs = session_references(session)
    config = recursive.RecursiveConfig()
    py = recursive.create(nominal, ESTIMATE_NAMES, config, np.float32)
    p64 = recursive.create(nominal, ESTIMATE_NAMES, config, np.float64)
    c = CEstimator(nominal, ESTIMATE_NAMES, config)
    t_py = t_c = 0.0
    differing = 0
    for rows in session.frame_slices():
        frame = (session.x_px[rows], session.y_px[rows], refs.r[rows], refs.usable[rows])
        t0 = time.perf_counter()
        firmware.estimator_update(py, *frame, precision)
        t1 = time.perf_counter()
        c.update(*frame, precision=precision)
        t2 = time.perf_counter()
        t_py, t_c = t_py + t1 - t0, t_c + t2 - t1
        differing += recursive.save_state(py) != c.save_state()
        recursive.update(p64, *frame)
    sd = np.sqrt(np.diag(recursive.covariance(py)))
    theta = recursive.state_vector(py)
    c_diff = float(np.max(np.abs((c.state_vector() - theta)[py.idx] / sd)))
    f64_diff = float(np.max(np.abs((recursive.state_vector(p64) - theta)[py.idx] / sd)))
    return c_diff, f64_diff, t_py / n_frames, t_c / n_frames, differing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--sessions", type=int, default=10)
    args = parser.parse_args()
    nominal = params_from_dict(NOMINAL)
    for precision in ("float32", "fixed"):
        rows = [one_session(nominal, args.frames, seed, precision) for seed in range(1, args.sessions + 1)]
        c_diff, f64_diff, t_py, t_c, differing = (np.array(col) for col in zip(*rows, strict=True))
        print(
            f"{precision}: frames with differing saved states {int(differing.sum())} of "
            f"{args.frames * args.sessions}; |C - Python| / sigma after {args.frames} frames over {args.sessions} "
            "sessions: "
            f"max {c_diff.max():.4f}, median {np.median(c_diff):.4f}; |float64 - float32| / sigma: max "
            f"{f64_diff.max():.4f}, median {np.median(f64_diff):.4f}; per frame: Python {1e3 * t_py.mean():.2f} ms, "
            f"C {1e3 * t_c.mean():.3f} ms ({t_py.mean() / t_c.mean():.0f}x)"
        )


if __name__ == "__main__":
    main()
