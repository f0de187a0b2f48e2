"""Study: the onboard recursive estimator's error against the Cramer-Rao bound, per parameter, over N seeds.

Each seed is one seed-004 session (``hostlink.sky.simulate.seed004_config``: Hipparcos stars to Hp 6, >= 10 stars per
frame, 0.05 px) or one synthetic run (``hostlink.api.synth_frames``, 10-30 stars uniformly on the detector), replayed
from seed 004's cold start (f 72 mm, principal point (512, 512), no distortion). For each parameter it prints

* err/CRB: RMS over the seeds of (estimate - truth) / CRB, CRB = sqrt(diag(J^-1)), J the 2n-3 pair information of the
  same frames at the truth (the bound of the measurement model; the estimator's own weighting is not used). An
  efficient estimator gives 1; with n seeds the RMS of n standard normals has a relative spread of about
  1 / sqrt(2 n) (chi(n) / sqrt(n)), so 8 seeds resolve 1.0 from 1.3 at about 1.2 sigma each and the 10-parameter
  Mahalanobis ratio sqrt(e J e / 10) far better.
* mean err/CRB: the bias part (the mean of n standard normals has spread 1 / sqrt(n)).
* sigma/CRB: the filter's reported 1-sigma against the bound.
* f32-f64: the largest |float32 - float64| / CRB over the seeds (with --compare64).

    .venv/bin/python benchmarks/recursive_crb_study.py [--seeds 8] [--source sky|synth] [--compare64]
        [--set burn_in_frames=300 --set burn_in_power=2]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from hostlink.api import interstar_batch_ml as batch_ml
from hostlink.api import seed004_paper_start, sky_frames, synth_frames
from onboard import recursive
from onboard.params import ESTIMATE_NAMES

SEED004_PAPER_START = seed004_paper_start()


def run_estimator(frames, config, dtype, nominal=SEED004_PAPER_START):
    st = recursive.create(nominal, ESTIMATE_NAMES, config, dtype)
    for x, y, r, ok in frames:
        recursive.update(st, x, y, r, ok)
    return st


def study(seeds, source, n_frames, config, compare64, verbose=True, nominal=SEED004_PAPER_START, batch=False):
    """Per-seed normalised errors (S, 10), sigma ratios (S, 10), f32-f64 differences (S, 10), Mahalanobis (S,),
    and (with ``batch``) the batch ML's normalised errors (S, 10)."""
    get = sky_frames if source == "sky" else synth_frames
    errs, sigs, diffs, maha, ml = [], [], [], [], []
    for seed in seeds:
        t0 = time.perf_counter()
        camera, frames, info = get(seed, n_frames)
        crb = np.sqrt(np.diag(np.linalg.inv(info)))
        st = run_estimator(frames, config, np.float32, nominal)
        err = recursive.state_vector(st) - camera.model_vector()
        errs.append(err / crb)
        maha.append(float(err @ info @ err / 10))
        sigs.append(np.sqrt(np.diag(recursive.covariance(st))) / crb)
        if compare64:
            st64 = run_estimator(frames, config, np.float64, nominal)
            diffs.append((recursive.state_vector(st) - recursive.state_vector(st64)) / crb)
        if batch:
            ml.append((batch_ml(camera, frames) - camera.model_vector()) / crb)
        if verbose:
            print(
                f"  seed {seed:3d}: "
                + " ".join(f"{v:+5.2f}" for v in errs[-1])
                + f"  | maha {np.sqrt(maha[-1]):.2f}  ({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
    return np.array(errs), np.array(sigs), np.array(diffs), np.array(maha), np.array(ml)


def parse_set(items):
    fields = {f.name: f for f in dataclasses.fields(recursive.RecursiveConfig)}
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in fields:
            raise SystemExit(f"--set: unknown RecursiveConfig field {key!r}")
        out[key] = type(getattr(recursive.RecursiveConfig(), key))(eval(value, {}, {}))  # noqa: S307 (study tool)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--source", choices=("sky", "synth"), default="sky")
    parser.add_argument("--compare64", action="store_true", help="also run float64 and report |f32 - f64| / CRB")
    parser.add_argument("--batch", action="store_true", help="also compute the batch ML reference (slower)")
    parser.add_argument("--nominal-pp", metavar="X,Y", help="start from this principal point instead of (512, 512)")
    parser.add_argument("--nominal-f", type=float, help="start from this focal length [mm] instead of 72")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    args = parser.parse_args()
    config = recursive.RecursiveConfig(**parse_set(args.set))
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    nominal = SEED004_PAPER_START
    if args.nominal_pp:
        nominal = dataclasses.replace(nominal, principal_point_px=tuple(float(v) for v in args.nominal_pp.split(",")))
    if args.nominal_f:
        nominal = nominal.with_focal_length_mm(args.nominal_f)
    print(f"{args.source} sessions, {args.frames} frames, seeds {seeds[0]}..{seeds[-1]}, overrides {args.set or '-'}")
    print("           " + " ".join(f"{n:>5s}" for n in ESTIMATE_NAMES))
    errs, sigs, diffs, maha, ml = study(
        seeds, args.source, args.frames, config, args.compare64, nominal=nominal, batch=args.batch
    )
    n = len(seeds)
    print("RMS err/CRB    " + " ".join(f"{v:5.2f}" for v in np.sqrt(np.mean(errs**2, axis=0))))
    print("mean err/CRB   " + " ".join(f"{v:+5.2f}" for v in np.mean(errs, axis=0)))
    print("sigma/CRB      " + " ".join(f"{v:5.2f}" for v in np.mean(sigs, axis=0)))
    if args.batch:
        print("batch ML       " + " ".join(f"{v:5.2f}" for v in np.sqrt(np.mean(ml**2, axis=0))))
        print("RMS (rec-ML)   " + " ".join(f"{v:5.2f}" for v in np.sqrt(np.mean((errs - ml) ** 2, axis=0))))
    if args.compare64:
        print("max|f32-f64|   " + " ".join(f"{v:5.3f}" for v in np.max(np.abs(diffs), axis=0)))
    print(
        f"all ten: sqrt(mean e J e / 10) = {np.sqrt(np.mean(maha)):.3f}; "
        f"one-sigma spread of a per-parameter RMS over {n} seeds ~ {1 / np.sqrt(2 * n):.2f}"
    )


if __name__ == "__main__":
    main()
