"""``hostlink simulate``: simulated observations of the real sky through a given camera (docs/file-formats.md).

Writes SESSION.csv or SESSION.parquet (with ra_deg, dec_deg: geocentric apparent place) and SESSION.truth.json
beside it.
The simulation itself is ``hostlink.sky.simulate``.
"""

from __future__ import annotations

import argparse
import math
import sys

from hostlink.api import UserError
from hostlink.commands.siteopts import add_site_arguments, site_and_weather

HELP = "simulate a session of real-sky (Hipparcos) observations through a camera, with its truth"
DESCRIPTION = (
    "Simulate a session of star observations: Hipparcos stars at their geocentric apparent place at each frame's time "
    "(pyerfa), random or scripted attitudes, the true camera with full Weng distortion and Gaussian centroid noise. "
    "Writes SESSION.csv or SESSION.parquet (with ra_deg,dec_deg) and SESSION.truth.json (camera, per-frame attitude C "
    "with b = C r, per-frame focal length, misidentified and false rows). With --site the observed directions get the "
    "diurnal aberration of the site's rotation (up to 0.32\"), and with --weather also ERFA's refraction (the "
    "observed place of erfa.atco13), while ra_deg,dec_deg stay the geocentric apparent place. --preset seed004 "
    "reproduces seed 004's simulation setup: a 1024 x 1024 px, 12 um, 10 deg camera with f 70.2262 mm, principal point "
    "(500, 530) px and radial distortion (the true-camera.json of `hostlink example`), Hp <= 6, >= 10 stars, 0.05 px, "
    "1000 frames."
)

PRESETS = ("seed004",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--camera",
        metavar="CAMERA.json",
        help="true camera parameter file, optional with --preset (a path, or builtin:NAME for one shipped with "
        "the package, e.g. builtin:seed004_camera)",
    )
    parser.add_argument("--frames", type=int, metavar="N", help="number of frames (preset seed004: 1000)")
    parser.add_argument(
        "--out",
        required=True,
        metavar="SESSION.csv",
        help="session file to write: CSV, or Parquet when the name ends in .parquet (columnar: exact float64, "
        "half the size, faster to read; docs/file-formats.md)",
    )
    parser.add_argument(
        "--preset",
        choices=PRESETS,
        help="a published setup (seed004: the simulation of Ye and Yang, Optics and Precision Engineering 25(9), "
        "2017); explicit options override it",
    )
    parser.add_argument("--noise-px", type=float, metavar="S", help="centroid noise, 1-sigma per axis (default 0.05)")
    parser.add_argument("--min-stars", type=int, metavar="K", help="fewest stars per frame (default 10)")
    parser.add_argument("--max-stars", type=int, metavar="K", help="most stars per frame, brightest kept (default 30)")
    parser.add_argument("--maglim", type=float, metavar="M", help="faintest Hipparcos magnitude Hp (default 6)")
    parser.add_argument("--seed", type=int, metavar="N", help="random seed (default 0)")
    parser.add_argument("--t0", metavar="ISO", help="time of frame 0, UTC (default 2026-03-14T02:10:00.000Z)")
    parser.add_argument("--interval", type=float, metavar="SECONDS", help="time between frames (default 1)")
    parser.add_argument("--misid", type=float, metavar="FRACTION", help="fraction of stars given a wrong identity")
    parser.add_argument(
        "--false-stars", type=float, metavar="FRACTION", help="false (unidentified) stars per real star (Poisson)"
    )
    parser.add_argument("--focal-drift-um", type=float, metavar="A", help="thermal focal-length drift amplitude, um")
    parser.add_argument("--focal-drift-period", type=float, metavar="FRAMES", help="drift period (default 3000)")
    parser.add_argument(
        "--zenith-range", metavar="MIN_DEG,MAX_DEG", help="boresight zenith distances for --site (default 0,75)"
    )
    parser.add_argument(
        "--attitudes", metavar="ATTITUDE.csv", help="scripted attitudes: CSV with c11..c33 (b = C r), one row a frame"
    )
    add_site_arguments(parser)


def _fraction_pair(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"--zenith-range {text!r}: expected MIN_DEG,MAX_DEG, e.g. 0,75") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise UserError(f"--zenith-range {text!r}: expected finite numbers")
    return lo, hi


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from hostlink.api import (
        SimConfig,
        load_params,
        progress_bar,
        read_attitude_matrices,
        seed004_config,
        truth_path_for,
        write_simulation,
    )

    site, weather = site_and_weather(args)
    attitudes = read_attitude_matrices(args.attitudes) if args.attitudes else None
    if attitudes is not None and args.frames is None:
        args.frames = int(attitudes.shape[0])
    if args.preset == "seed004":
        cfg = seed004_config()
    else:
        if not args.camera:
            raise UserError("--camera is required (or choose a --preset)")
        if args.frames is None:
            raise UserError("--frames is required (or choose a --preset)")
        cfg = None
    camera = load_params(args.camera) if args.camera else cfg.camera
    if cfg is None:
        cfg = SimConfig(camera=camera, frames=args.frames)
    overrides = {
        "camera": camera,
        "frames": args.frames,
        "noise_px": args.noise_px,
        "min_stars": args.min_stars,
        "max_stars": args.max_stars,
        "maglim": args.maglim,
        "seed": args.seed,
        "t0_iso": args.t0,
        "frame_interval_s": args.interval,
        "misid_fraction": args.misid,
        "false_star_fraction": args.false_stars,
        "focal_drift_um": args.focal_drift_um,
        "focal_drift_period_frames": args.focal_drift_period,
        "site": site,
        "weather": weather,
        "dut1_s": args.dut1,
        "zenith_range_deg": _fraction_pair(args.zenith_range) if args.zenith_range else None,
        "attitudes": attitudes,
    }
    cfg = replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    if cfg.min_stars > cfg.max_stars and args.max_stars is None:
        cfg = replace(cfg, max_stars=cfg.min_stars)
    # a bar only where simulating takes long enough to watch (a few thousand frames and up)
    truth_path = truth_path_for(args.out)
    # streamed to disk chunk by chunk: memory bounded by one chunk whatever --frames (issue 31)
    with progress_bar("simulating", int(cfg.frames), enabled=cfg.frames >= 2000) as advance:
        frames, rows = write_simulation(cfg, args.out, truth_path, progress=lambda done, _total: advance(done))
    print(f"wrote {frames} frames, {rows} stars to {args.out} (truth: {truth_path})", file=sys.stdout)
    return 0
