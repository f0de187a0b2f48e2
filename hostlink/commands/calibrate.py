"""``hostlink calibrate``: batch ground calibration of a session (INTERFACES.md)."""

from __future__ import annotations

import argparse

from hostlink.commands.siteopts import add_site_arguments, site_and_weather
from hostlink.errors import UserError

HELP = "batch ground calibration of a session (default: bundle adjustment, the most accurate method)"
DESCRIPTION = (
    "Estimate the camera parameters from a session of identified stars. Methods: bundle (default; camera plus "
    "per-frame attitude, maximum likelihood), cosine and sine (seed 000 interstar least squares, f and principal "
    "point), improved-cosine and improved-sine (seed 000 two-step iteration with Weng distortion), seed004 (seed 004 "
    "three-step Levenberg-Marquardt). Misidentified stars are found and dropped. With --site the reference "
    "directions get the diurnal aberration of the site's rotation (up to 0.32\"), and with --weather they are "
    "also refracted, before the fit. The result is a camera parameter file plus sigma, "
    "residual statistics, degeneracies and rejected-star counts."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from onboard.params import ESTIMATE_NAMES

    parser.add_argument("session", metavar="SESSION.csv", help="session file (INTERFACES.md)")
    parser.add_argument("--nominal", required=True, metavar="NOMINAL.json", help="nominal camera parameter file")
    parser.add_argument("--out", required=True, metavar="RESULT.json", help="result parameter file to write")
    parser.add_argument(
        "--method",
        default="bundle",
        choices=("bundle", "cosine", "sine", "improved-cosine", "improved-sine", "seed004"),
        help="calibration method (default bundle)",
    )
    parser.add_argument(
        "--estimate",
        metavar="NAMES",
        help=f"comma-separated parameters to estimate (default: the method's own set; all = "
        f"{','.join(ESTIMATE_NAMES)})",
    )
    parser.add_argument(
        "--noise-px",
        type=float,
        metavar="S",
        help="centroid noise per axis [px] for the reported sigma (default: from the residuals)",
    )
    parser.add_argument("--max-iter", type=int, default=100, metavar="N", help="most iterations (default 100)")
    parser.add_argument("--plot", metavar="DIR", help="write residual-field and convergence PNGs into DIR")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_site_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from hostlink.calibration.run import calibrate_session, result_extras
    from hostlink.files.params import load_params, save_params
    from hostlink.files.session import check_on_detector, read_session
    from onboard.recursive import parse_estimate_names

    try:
        estimate = None if args.estimate is None else parse_estimate_names(args.estimate)
    except ValueError as exc:
        raise UserError(f"--estimate {args.estimate!r}: {exc}") from None
    site, weather = site_and_weather(args)
    nominal = load_params(args.nominal)
    session = read_session(args.session)
    if len(session) == 0:
        raise UserError(f"{args.session}: no star rows")
    check_on_detector(session, nominal.image_size_px, args.session, args.nominal)
    large = len(session) > 200_000

    def progress(entry: dict) -> None:
        if not args.quiet and large:
            print(f"  iteration {entry['iteration']}: cost {entry['cost']:.6g}", flush=True)

    outcome, references = calibrate_session(
        session, nominal, args.method, estimate, args.noise_px, args.max_iter, site, weather, args.dut1, progress
    )
    save_params(args.out, outcome.params, result_extras(outcome, references))
    if not args.quiet:
        print(
            f"calibrate: {outcome.data.n_obs + outcome.rejected['total_stars']} identified stars, "
            f"{outcome.data.n_obs} used in {outcome.data.n_frames} frames ({references.n_unidentified} unidentified "
            f"rows ignored); references from {references.source}; "
            f"refraction: {references.refraction}"
        )
        _print_report(outcome, args.out)
    if args.plot:
        from hostlink.calibration.plots import write_calibration_plots

        write_calibration_plots(Path(args.plot), outcome, nominal.image_size_px)
        if not args.quiet:
            print(f"plots written to {args.plot}/residual_field.png and convergence.png")
    return 0


def _print_report(outcome, out_path: str) -> None:
    sig = outcome.sigma()
    p = outcome.params
    rows = [
        ("f [mm]", p.focal_length_mm, sig["focal_length_mm"]),
        ("x0 [px]", p.principal_point_px[0], sig["principal_point_px"][0]),
        ("y0 [px]", p.principal_point_px[1], sig["principal_point_px"][1]),
    ]
    rows += [(k, getattr(p.distortion, k), sig["distortion"][k]) for k in ("k1", "k2", "k3", "p1", "p2", "s1", "s2")]
    b, a = outcome.before, outcome.after
    stats = [
        ("residual RMS [px]", b["rms_px"], a["rms_px"]),
        ("residual max [px]", b["max_px"], a["max_px"]),
        ("residual RMS [arcsec]", b["rms_arcsec"], a["rms_arcsec"]),
        ("residual max [arcsec]", b["max_arcsec"], a["max_arcsec"]),
        ("interstar RMS [rad]", outcome.interstar_before_rad, outcome.interstar_after_rad),
    ]
    rej = outcome.rejected
    lines_after = [
        f"rejected stars: {rej['total_stars']} ({rej['voting']} by interstar voting, {rej['gating']} by residual "
        f"gating; {rej['frames_dropped']} frames dropped)",
        f"noise: {outcome.sigma_estimated_px:.4f} px estimated, {outcome.sigma_px:.4f} px used for sigma; "
        f"{len(outcome.history)} iterations{'' if outcome.converged else ' (NOT converged)'}",
    ]
    lines_after += [f"degeneracy: {m}" for m in outcome.degeneracies["messages"]]
    lines_after.append(f"written: {out_path}")

    def fmt_sigma(v):
        return "fixed" if v == 0.0 else ("unobservable" if v is None else f"{v:.3g}")

    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console()
    t = Table(title=f"hostlink calibrate: method {outcome.method}")
    t.add_column("parameter")
    t.add_column("value", justify="right")
    t.add_column("1 sigma", justify="right")
    for name, value, s in rows:
        t.add_row(escape(name), f"{value:.8g}", fmt_sigma(s))
    console.print(t)
    t2 = Table()
    t2.add_column("statistic")
    t2.add_column("before", justify="right")
    t2.add_column("after", justify="right")
    for name, before, after in stats:
        t2.add_row(escape(name), f"{before:.4g}", f"{after:.4g}")
    console.print(t2)
    for line in lines_after:
        console.print(escape(line), highlight=False)
