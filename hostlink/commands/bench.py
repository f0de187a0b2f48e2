"""``hostlink bench``: the main job, end to end against an emulated sensor (see ``hostlink.mission.run``)."""

from __future__ import annotations

import argparse

from hostlink.commands.siteopts import add_site_arguments

HELP = "the main job: emulated sensor -> stream -> calibrate -> safe upload -> onboard drift tracking -> report"
DESCRIPTION = (
    "Runs the whole mission with no hardware and no arguments: an emulated sensor (a separate process running the "
    "onboard firmware) whose true camera differs from its nominal one, as after launch, streams a session over a "
    "real link; the host calibrates it, uploads the parameters safely and verifies them by read-back; the onboard "
    "recursive estimator then runs on and tracks a thermal focal-length drift. The report (summary.json and PNG "
    "plots) goes to --out; a short table goes to the terminal. Longer or harsher runs: --frames, --drift-frames, "
    "--noise-px, --misid, --site/--weather (a ground site with refraction), --transport."
)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="bench-report", metavar="DIR", help="report folder (default bench-report/)")
    parser.add_argument(
        "--transport",
        default="serial",
        choices=("serial", "can", "modbus"),
        help="link to the emulated sensor (default serial, on a pty)",
    )
    _add_drift_arguments(parser)
    _add_sky_arguments(parser)
    _add_firmware_arguments(parser)
    add_site_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_drift_arguments(parser: argparse.ArgumentParser) -> None:
    """The run: calibration frames, then the drift phase (frames, amplitude, period)."""
    parser.add_argument(
        "--frames",
        type=_positive_int,
        default=600,
        metavar="N",
        help="frames streamed for the ground calibration (default 600)",
    )
    parser.add_argument(
        "--drift-frames",
        type=_positive_int,
        default=3000,
        metavar="N",
        help="frames of the drift phase, tracked by the onboard estimator (default 3000)",
    )
    parser.add_argument(
        "--drift-um",
        type=float,
        default=None,
        metavar="UM",
        help="amplitude of the sinusoidal focal-length drift [um] (default: 8.6e-5 of the nominal focal length, 6 um "
        "on the built-in 70 mm camera's: a lens's thermal drift scales with its focal length)",
    )
    parser.add_argument(
        "--drift-period",
        type=float,
        default=None,
        metavar="FRAMES",
        help="period of the drift [frames] (default: the drift phase's length)",
    )


def _add_sky_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulated sky and camera: noise, misidentified stars, camera or nominal set, seed, magnitudes, stars."""
    parser.add_argument(
        "--noise-px", type=float, default=0.05, metavar="S", help="centroid noise, 1-sigma per axis [px] (default 0.05)"
    )
    parser.add_argument(
        "--misid", type=float, default=0.0, metavar="FRACTION", help="fraction of misidentified stars (default 0)"
    )
    parser.add_argument(
        "--camera",
        metavar="CAMERA.json",
        help="the sensor's true camera (default: built in: a 1024 x 1024 px, 12 um, 70 mm, 10 deg camera (seed 004's "
        "design) after a launch shock: focal length and principal point moved, radial, decentering and thin-prism "
        "distortion)",
    )
    parser.add_argument(
        "--nominal",
        metavar="NOMINAL.json",
        help="the sensor's factory parameters, a path or builtin:NAME (default builtin:seed004_nominal: that "
        "camera's design values, shipped with the package: f 70 mm, 12 um, 1024 x 1024 px, principal point at the "
        "image centre, no distortion; `hostlink example` writes "
        "them as nominal.json)",
    )
    parser.add_argument("--seed", type=int, default=1, help="simulator seed (default 1)")
    parser.add_argument(
        "--maglim",
        type=float,
        default=6.0,
        metavar="M",
        help="faintest Hipparcos magnitude Hp simulated (default 6; raise it for a narrow field)",
    )
    parser.add_argument(
        "--min-stars", type=_positive_int, default=10, metavar="K", help="fewest stars per frame (default 10)"
    )
    parser.add_argument(
        "--max-stars",
        type=_positive_int,
        default=30,
        metavar="K",
        help="most stars per frame, brightest kept (default 30)",
    )


def _add_firmware_arguments(parser: argparse.ArgumentParser) -> None:
    """The sensor inside: the estimator precision and the firmware (Python or C)."""
    parser.add_argument(
        "--precision",
        choices=("float32", "fixed"),
        default="float32",
        help="the emulated sensor's arithmetic: float32 (a single-precision FPU, the default) or fixed (no FPU: the "
        "onboard estimator's per-star front end in integers, its filter in soft float32)",
    )
    parser.add_argument(
        "--firmware",
        choices=("python", "c"),
        default="python",
        help="the emulated sensor's firmware: python (the reference model, the default) or c (the C core of onboard/c, "
        "built once with this machine's C compiler)",
    )


def run(args: argparse.Namespace) -> int:
    import math
    from pathlib import Path

    from hostlink.api import BenchConfig, UserError, load_params, run_bench
    from hostlink.commands.siteopts import site_and_weather

    if not (math.isfinite(args.noise_px) and 0 < args.noise_px <= 5):
        raise UserError(f"--noise-px must be in (0, 5] px, got {args.noise_px}")
    if not 0 <= args.misid < 0.5:
        raise UserError(f"--misid must be a fraction in [0, 0.5), got {args.misid}")
    if args.drift_um is not None and not (math.isfinite(args.drift_um) and 0 <= args.drift_um <= 1000):
        raise UserError(f"--drift-um must be in [0, 1000] um, got {args.drift_um}")
    site, weather = site_and_weather(args)
    if site is not None and weather is None:
        raise UserError("--site needs --weather for a ground session (refraction depends on it)")
    cfg = BenchConfig(
        out_dir=Path(args.out),
        transport=args.transport,
        cal_frames=args.frames,
        drift_frames=args.drift_frames,
        noise_px=args.noise_px,
        misid_fraction=args.misid,
        drift_um=args.drift_um,
        drift_period_frames=float(args.drift_period or args.drift_frames),
        seed=args.seed,
        site=site,
        weather=weather,
        maglim=args.maglim,
        min_stars=args.min_stars,
        max_stars=args.max_stars,
        precision=args.precision,
        firmware=args.firmware,
    )
    if args.camera:
        cfg.camera = load_params(args.camera)
    if args.nominal:
        cfg.nominal = load_params(args.nominal)
    try:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {args.out}: cannot create the report folder ({exc.strerror})") from None
    summary = run_bench(cfg, say=print, show_progress=not args.quiet)
    _print_table(summary)
    print(f"report: {Path(args.out) / 'summary.json'} and PNG plots in {args.out}/ ({summary['elapsed_s']:.0f} s)")
    return 0


def _print_table(summary: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    from hostlink.api import summary_table

    table = Table(title=f"hostlink bench ({summary['transport']}, {summary['precision']} sensor)")
    for col in ("quantity", "before (nominal)", "after"):
        table.add_column(col)
    for row in summary_table(summary):
        table.add_row(*row)
    Console().print(table)
