"""Benchmark: one identified session calibrated with the noise floor constant and as the data choose (constant or
growing with the field radius, docs/calibration.md "A floor that grows towards the corners"), side by side: the model
chosen and its components, the residuals, the stars rejected, the focal length and principal point with their stated
1-sigma (and, given the true camera, their errors in those sigmas), and the CPU time of each calibration (in
process, best of ``--repeat``). Run under an older tree (PYTHONPATH) it calibrates once, as that tree does ("before").

    PYTHONPATH=. .venv/bin/python benchmarks/bench_noise_model.py SESSION --nominal NOMINAL [--truth TRUE] [--json OUT]
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
from pathlib import Path


def _run(session, nominal, model: str | None, repeat: int) -> tuple[object, float]:
    from hostlink.calibration.run import calibrate_session

    kwargs = {"keep_failed": True} if model is None else {"keep_failed": True, "noise_model": model}
    best = float("inf")
    for _ in range(repeat):  # process (CPU) time: the machine's other load does not count
        t0 = time.process_time()
        outcome, _ = calibrate_session(session, nominal, **kwargs)
        best = min(best, time.process_time() - t0)
    return outcome, best


def _figures(outcome, seconds: float, truth) -> dict:
    sig = outcome.sigma()
    p = outcome.params
    out = {
        "cpu_s": seconds,
        "noise_model": getattr(outcome, "noise_model", None),
        "noise_scale": outcome.noise_scale,
        "noise_floor_px": outcome.noise_floor_px,
        "noise_floor_edge_px": getattr(outcome, "noise_floor_edge_px", outcome.noise_floor_px),
        "rms_px": outcome.after.get("rms_px"),
        "rms_px_clipped": outcome.after.get("rms_px_clipped"),
        "stars_used": outcome.n_stars_used,
        "rejected": outcome.rejected,
        "focal_length_mm": p.focal_length_mm,
        "principal_point_px": list(p.principal_point_px),
        "sigma": {"focal_length_mm": sig["focal_length_mm"], "principal_point_px": sig["principal_point_px"]},
    }
    if truth is not None:
        out["error"] = {
            "focal_length_mm": p.focal_length_mm - truth.focal_length_mm,
            "x0_px": p.principal_point_px[0] - truth.principal_point_px[0],
            "y0_px": p.principal_point_px[1] - truth.principal_point_px[1],
        }
        s_f, (s_x, s_y) = sig["focal_length_mm"], sig["principal_point_px"]
        e = out["error"]
        pairs = ((e["focal_length_mm"], s_f), (e["x0_px"], s_x), (e["y0_px"], s_y))
        out["error_in_sigmas"] = [err / s if s > 0 else None for err, s in pairs]  # None: held fixed, not estimated
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("session")
    parser.add_argument("--nominal", required=True)
    parser.add_argument("--truth", help="the true camera's parameter file (a rendered set): errors in stated sigmas")
    parser.add_argument("--repeat", type=int, default=1, help="calibrations per model, the fastest timed")
    parser.add_argument("--json", metavar="OUT")
    args = parser.parse_args()
    from hostlink.errors import UserError

    try:
        result = _compare(args)
    except UserError as exc:  # a missing or unreadable file, a session that cannot be calibrated: one line
        print(f"bench_noise_model: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str))
    return 0


def _compare(args: argparse.Namespace) -> dict:
    """Each noise model's figures (:func:`_figures`) on the session, each printed as it is measured."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.files.params import load_params
    from hostlink.files.session import read_session

    session = read_session(args.session)
    nominal = load_params(args.nominal)
    truth = load_params(args.truth) if args.truth else None
    models = ("constant", "auto") if "noise_model" in inspect.signature(calibrate_session).parameters else (None,)
    result = {}
    for model in models:
        outcome, seconds = _run(session, nominal, model, args.repeat)
        result[model or "before"] = _figures(outcome, seconds, truth)
        print(f"{model or 'before'}: {json.dumps(result[model or 'before'], default=str)}")
    return result


if __name__ == "__main__":
    sys.exit(main())
