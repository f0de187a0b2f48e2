"""``hostlink calibrate``: batch ground calibration of a session (INTERFACES.md)."""

from __future__ import annotations

import argparse
import math

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


def _parse_estimate(text: str | None) -> tuple[str, ...] | None:
    from onboard.params import ESTIMATE_NAMES

    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in ESTIMATE_NAMES]
    if unknown or not names:
        raise UserError(
            f"--estimate {text!r}: unknown name {unknown[0] if unknown else '(empty)'!r} "
            f"(allowed: {','.join(ESTIMATE_NAMES)})"
        )
    return tuple(n for n in ESTIMATE_NAMES if n in names)


def _json_safe(value):
    """Replace non-finite floats by None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from hostlink.calibration.references import calibration_data_from_session
    from hostlink.calibration.run import calibrate, result_extras
    from hostlink.files.params import load_params, save_params
    from hostlink.files.session import check_on_detector, read_session
    from onboard.params import ParameterError, validate_params

    estimate = _parse_estimate(args.estimate)
    if args.noise_px is not None and not (math.isfinite(args.noise_px) and args.noise_px > 0):
        raise UserError(f"--noise-px {args.noise_px}: expected a positive number of pixels")
    if args.max_iter < 1:
        raise UserError(f"--max-iter {args.max_iter}: expected at least 1")
    site, weather = site_and_weather(args)
    nominal = load_params(args.nominal)
    session = read_session(args.session)
    if len(session) == 0:
        raise UserError(f"{args.session}: no star rows")
    check_on_detector(session, nominal.image_size_px, args.session, args.nominal)
    data, info = calibration_data_from_session(session, site, weather, args.dut1)
    say = (lambda *a: None) if args.quiet else print
    say(
        f"calibrate: {data.n_obs} identified stars in {data.n_frames} frames ({info.n_unidentified} unidentified "
        f"rows ignored); references from {info.source}; refraction: {info.refraction}"
    )

    def progress(entry: dict) -> None:
        if not args.quiet and data.n_obs > 200_000:
            print(f"  iteration {entry['iteration']}: cost {entry['cost']:.6g}", flush=True)

    try:
        outcome = calibrate(data, nominal, args.method, estimate, args.noise_px, args.max_iter, progress)
    except ValueError as exc:
        raise UserError(f"calibration failed: {exc}") from None
    try:
        validate_params(outcome.params)
    except ParameterError as exc:
        raise UserError(f"the calibrated parameters are not usable ({exc}); check the nominal file") from None
    extras = result_extras(outcome)
    extras["references"] = {
        "source": info.source,
        "refraction": info.refraction,
        "unidentified_rows": info.n_unidentified,
    }
    save_params(args.out, outcome.params, _json_safe(extras))
    if not args.quiet:
        _print_report(outcome, args.out)
    if args.plot:
        from hostlink.calibration.bundle import residuals
        from hostlink.calibration.plots import convergence_png, residual_field_png

        out_dir = Path(args.plot)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--plot {out_dir}: cannot create ({exc.strerror})") from None
        e = residuals(outcome.data, outcome.theta, outcome.attitudes)
        residual_field_png(
            out_dir / "residual_field.png",
            outcome.data.x_px,
            outcome.data.y_px,
            e,
            nominal.image_size_px,
            f"{outcome.method}: mean residual per cell after calibration (RMS {outcome.after['rms_px']:.4f} px)",
        )
        convergence_png(out_dir / "convergence.png", outcome.history, f"{outcome.method}: convergence")
        say(f"plots written to {out_dir}/residual_field.png and convergence.png")
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

    try:
        from rich.console import Console
        from rich.markup import escape
        from rich.table import Table
    except ImportError:  # plain text when rich is missing
        print(f"method {outcome.method}")
        for name, value, s in rows:
            print(f"  {name:10s} {value: .8g}  +/- {fmt_sigma(s)}")
        for name, before, after in stats:
            print(f"  {name:24s} {before:.4g} -> {after:.4g}")
        for line in lines_after:
            print(line)
        return
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
