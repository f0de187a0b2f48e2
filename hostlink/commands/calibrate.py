"""``hostlink calibrate``: batch ground calibration of a session (docs/file-formats.md)."""

from __future__ import annotations

import argparse

from hostlink.api import UserError
from hostlink.commands.jsonopt import add_json_argument
from hostlink.commands.siteopts import add_site_arguments, site_and_weather

#: Sessions of more stars than this print one line per iteration of the fit (it then takes seconds to minutes);
#: smaller ones only the report.
ITERATION_LINES_ABOVE_STARS = 200_000

HELP = "batch ground calibration of a session (default: bundle adjustment, the most accurate method)"
DESCRIPTION = (
    "Estimate the camera parameters from a session of identified stars. Methods: bundle (default; camera plus "
    "per-frame attitude, maximum likelihood), cosine and sine (seed 000 interstar least squares, f and principal "
    "point), improved-cosine and improved-sine (seed 000 two-step iteration with Weng distortion), seed004 (seed 004 "
    "three-step Levenberg-Marquardt). Misidentified stars are found and dropped. With --site the reference "
    "directions get the diurnal aberration of the site's rotation (up to 0.32\"), and with --weather they are "
    "also refracted, before the fit. Before voting, the focal length (a nominal off by a factor 0.1 to 10 was "
    "tested) and the parity (a mirrored image is an error that says so) are found from the identified stars' "
    "interstar angles. "
    "Parameters the data cannot determine are held at nominal (the report says which and why; --estimate "
    "overrides). Star ids Hipparcos does not have are skipped. A session without time (t_utc empty) is calibrated "
    "against J2000 directions with the stated loss from annual aberration. A fit that does not converge or rejects "
    "more than half of the identified stars fails (exit 2) and writes nothing unless --keep-failed. The result is a "
    "camera parameter file plus sigma, residual statistics, degeneracies and rejected-star counts. The bundle "
    "method reads sessions of any length (one CSV, several files or a glob in time order, Parquet) chunk by chunk: "
    "memory bounded by one chunk, one pass over the frames per iteration, the same camera as the whole session in "
    "memory to rounding; the other methods, --rejected, --plot and --hold-out read one CSV whole; --dask maps the "
    "passes over a Dask cluster. A session with the optional sigma_px column (each star's 1-sigma centroid noise "
    "per axis, px) is weighted by it (bundle method; the seed methods do not use it), and the report gives the noise "
    "the fit finds relative to it and the noise floor it adds in quadrature (constant, or growing with field radius "
    "when the data choose it: --noise-model). A nominal whose image_size_px is not the size of the images the "
    "session records (image_width_px, image_height_px, from hostlink centroid) is refused in one line (exit 2), "
    "naming a 90-deg turn or a k x k binning when the sizes show one, as is one that a centroid lies off; a session "
    "without those columns is checked by its centroids alone."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _add_input_arguments(parser)
    _add_fit_and_report_arguments(parser)
    _add_chunked_arguments(parser)
    parser.add_argument(
        "--hold-out",
        type=int,
        metavar="K",
        help="also judge the calibration on stars it did not see: K more fits, each without one K-th of the frames, "
        "each judged on the stars of the frames it left out (attitude from the frame's other stars); reports their "
        "RMS [px] beside the fit's own residual, the figure to compare calibrations of the same images by "
        "(K >= 2; one CSV read whole)",
    )
    add_json_argument(parser, "the result (RESULT.json's object; also for a failure kept with --keep-failed)")
    add_site_arguments(parser)


def _add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """The session, the nominal set, the result file, the method and the parameters it estimates."""
    from hostlink.api import ESTIMATE_NAMES

    parser.add_argument(
        "session",
        nargs="+",
        metavar="SESSION",
        help="session file(s) (docs/file-formats.md): one CSV, or several files, a glob pattern or .parquet files "
        "read as one session in time order (the chunked path)",
    )
    parser.add_argument(
        "--nominal",
        required=True,
        metavar="NOMINAL.json",
        help="nominal camera parameter file (a path, or builtin:NAME for one shipped with the package, e.g. "
        "builtin:seed004_nominal)",
    )
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
        help=f"comma-separated parameters to estimate, as given (default: the method's own set; for bundle every "
        f"parameter the data determine; all = {','.join(ESTIMATE_NAMES)})",
    )


def _add_fit_and_report_arguments(parser: argparse.ArgumentParser) -> None:
    """What the fit reports and keeps: rejected stars, a failed result, the noise for sigma, iterations, plots."""
    parser.add_argument(
        "--rejected",
        metavar="FILE.csv",
        help="write every rejected star (row, line, frame, star_id, reason, residual_arcsec) to this CSV",
    )
    parser.add_argument(
        "--keep-failed",
        action="store_true",
        help="write the result file even when the calibration failed (marked 'failed'; the exit code stays 2)",
    )
    parser.add_argument(
        "--noise-px",
        type=float,
        metavar="S",
        help="centroid noise per axis [px] for the reported sigma (default: from the residuals)",
    )
    parser.add_argument(
        "--noise-model",
        default="auto",
        choices=("auto", "constant"),
        help="with sigma_px: the noise floor added in quadrature, constant over the field or growing with field "
        "radius as the data choose (auto, the default: radial only when its likelihood ratio says so), or held "
        "constant (constant)",
    )
    parser.add_argument("--max-iter", type=int, default=100, metavar="N", help="most iterations (default 100)")
    parser.add_argument(
        "--plot",
        metavar="DIR",
        help="write PNGs into DIR: residual_field_before.png (nominal camera), residual_field.png (calibrated) and "
        "convergence.png (residual RMS and step per iteration, its stages shaded)",
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _add_chunked_arguments(parser: argparse.ArgumentParser) -> None:
    """The chunked path: frames per chunk, a Dask cluster and its workers, the spool directory."""
    parser.add_argument(
        "--chunk-frames",
        type=int,
        metavar="N",
        help="read and fit the session N frames at a time, in memory bounded by one chunk whatever its length "
        "(bundle method, which reads in chunks of 10000 frames unless --rejected, --plot or --hold-out ask for the "
        "session whole)",
    )
    parser.add_argument(
        "--dask",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="map the chunks' normal equations over a Dask cluster: without ADDRESS (or 'local') a local cluster of "
        "--dask-workers processes; else a scheduler address such as tcp://host:8786 (its workers must see "
        "--spool-dir)",
    )
    parser.add_argument("--dask-workers", type=int, metavar="N", help="workers of the --dask local cluster (default 2)")
    parser.add_argument(
        "--spool-dir",
        metavar="DIR",
        help="directory for the chunked path's temporary arrays (default: the system's temporary directory)",
    )


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from hostlink.api import load_params, parse_estimate_names, result_extras, save_params

    args.quiet = args.quiet or args.json  # --json: the result object alone on stdout
    try:
        estimate = None if args.estimate is None else parse_estimate_names(args.estimate)
    except ValueError as exc:
        raise UserError(f"--estimate {args.estimate!r}: {exc}") from None
    site, weather = site_and_weather(args)
    nominal = load_params(args.nominal)
    if args.hold_out is not None and (args.hold_out < 2 or _chunked(args)):
        raise UserError(f"--hold-out {args.hold_out}: expected K >= 2 folds and one CSV read whole")
    calibrate = _calibrate_chunks if _chunked(args) else _calibrate_whole
    outcome, references = calibrate(args, nominal, estimate, site, weather)
    failure = outcome.failure()
    if args.rejected:
        from hostlink.api import write_rejected

        write_rejected(args.rejected, outcome.rejected_stars)
    if failure and not args.keep_failed:
        raise UserError(f"calibration failed: {failure}; nothing written (--keep-failed writes it anyway)")
    extras = result_extras(outcome, references)
    held_out = None
    if args.hold_out is not None and not failure:
        held_out = _held_out(args, nominal, estimate, site, weather)
        extras["held_out"] = held_out.as_dict()
    save_params(args.out, outcome.params, extras)
    if not args.quiet:
        unknown = references.unknown_rows
        ignored = references.n_unidentified - unknown.size
        print(
            f"calibrate: {outcome.n_stars_used + outcome.rejected['total_stars']} identified stars, "
            f"{outcome.n_stars_used} used in {outcome.n_frames_used} frames ({ignored} unidentified rows ignored); "
            f"references from {references.source}; refraction: {references.refraction}"
        )
        if unknown.size:
            lines = ", ".join(str(int(k) + 2) for k in unknown[:10]) + (", ..." if unknown.size > 10 else "")
            print(f"skipped {unknown.size} star_id(s) not in the Hipparcos catalogue on line(s) {lines}")
        _print_report(outcome, args.out, outcome.time_note, args.noise_model)
        if held_out is not None:
            print(
                f"held out: {held_out.n_stars} stars of {held_out.n_frames} frames, each judged by a fit without its "
                f"frame ({held_out.folds} folds): RMS {held_out.rms_px:.4g} px (those fits' own residual "
                f"{held_out.fit_rms_px:.4g} px)"
            )
    if args.plot:
        from hostlink.api import write_calibration_plots

        written = write_calibration_plots(Path(args.plot), outcome, nominal.image_size_px, nominal)
        if not args.quiet:
            print(f"plots written to {args.plot}: {', '.join(p.name for p in written)}")
    if args.json:
        from hostlink.api import params_json
        from hostlink.commands.jsonopt import print_json

        print_json(params_json(outcome.params, extras))
    if failure:
        raise UserError(f"calibration failed: {failure}; kept in {args.out} as asked (--keep-failed)")
    return 0


def _calibrate_whole(args: argparse.Namespace, nominal, estimate, site, weather):
    """One CSV read whole: every method, the --rejected list and the plots."""
    from hostlink.api import calibrate_session, check_on_detector, read_session

    path = args.session[0]
    session = read_session(path)
    if len(session) == 0:
        raise UserError(f"{path}: no star rows")
    check_on_detector(session, nominal.image_size_px, path, args.nominal)
    large = len(session) > ITERATION_LINES_ABOVE_STARS

    def progress(entry: dict) -> None:
        if not args.quiet and large:
            print(_iteration_line(entry), flush=True)

    return calibrate_session(
        session,
        nominal,
        args.method,
        estimate,
        args.noise_px,
        args.max_iter,
        site,
        weather,
        args.dut1,
        progress,
        keep_failed=True,  # decided here: the --rejected list is written either way
        noise_model=args.noise_model,
    )


def _held_out(args: argparse.Namespace, nominal, estimate, site, weather):
    """k-fold held-out judgement of the same calibration (hostlink.calibration.holdout.cross_validate)."""
    from hostlink.api import cross_validate, read_session

    return cross_validate(
        read_session(args.session[0]),
        nominal,
        args.hold_out,
        site,
        weather,
        args.dut1,
        method=args.method,
        estimate=estimate,
        noise_px=args.noise_px,
        max_iter=args.max_iter,
        noise_model=args.noise_model,
    )


def _iteration_line(entry: dict) -> str:
    """One line of progress per iteration of the fit (its history record)."""
    line = f"  iteration {entry['iteration']}: cost {entry['cost']:.6g}"
    if "step_sigmas" in entry:
        line += f", {entry['n_obs']} stars, step {entry['step_sigmas']:.3g} sigma"
    return line


def _chunked(args: argparse.Namespace) -> bool:
    """The chunked path, memory bounded by one chunk: the default of the bundle method for any source. The session is
    read whole only for one CSV and what needs all its stars at once: another method, --rejected, --plot or
    --hold-out (several files, a glob, Parquet, --chunk-frames and --dask are chunked whatever else is asked)."""
    one = args.session[0]
    several = len(args.session) > 1 or any(c in one for c in "*?[") or one.endswith(".parquet")
    if several or args.chunk_frames is not None or args.dask is not None:
        return True
    whole = args.method != "bundle" or args.rejected or args.plot or args.hold_out is not None
    return not whole


def _calibrate_chunks(args: argparse.Namespace, nominal, estimate, site, weather):
    """Any number of files, chunk by chunk (bundle only; no per-star output)."""
    from hostlink.api import calibrate_archive, estimated_session_rows, progress_bar

    if args.method != "bundle":
        raise UserError(
            f"--method {args.method}: the chunked path (--chunk-frames, --dask, several files, a glob, "
            ".parquet) calibrates with bundle only"
        )
    if args.rejected or args.plot:
        raise UserError(
            "--rejected and --plot need the session read whole: give one CSV file without --chunk-frames and --dask"
        )
    if args.dask_workers is not None and args.dask_workers < 1:
        raise UserError(f"--dask-workers {args.dask_workers}: expected at least 1")

    source = args.session[0] if len(args.session) == 1 else args.session
    total = estimated_session_rows(source)  # None when a file cannot be sized: the reader says why
    large = total is None or total > ITERATION_LINES_ABOVE_STARS

    def progress(entry: dict) -> None:
        if not args.quiet and large:
            print(_iteration_line(entry), flush=True)

    with progress_bar("reading session (stars)", total, enabled=not args.quiet) as advance:
        return calibrate_archive(
            source,
            nominal,
            args.chunk_frames,
            estimate,
            args.noise_px,
            args.max_iter,
            site,
            weather,
            args.dut1,
            progress,
            keep_failed=True,  # the failure is reported here, as for the whole session
            dask=args.dask,
            dask_workers=args.dask_workers,
            spool_dir=args.spool_dir,
            on_rows=advance,
            noise_model=args.noise_model,
        )


def _noise_line(outcome, noise_model: str = "auto") -> str:
    """The noise the fit found: in pixels, or relative to the session's per-star sigma_px when it weighted by it."""
    from hostlink.api import noise_model_text

    if outcome.noise_scale is not None:
        line = f"noise: {outcome.noise_scale:.3f} x the session's sigma_px (fitted; 1 when sigma_px is right) and "
        model = outcome.noise_model
        floor = (
            "a floor" if model and model["model"] == "radial" else f"a floor of {outcome.noise_floor_px or 0.0:.4f} px"
        )
        line += f"{floor} in quadrature, stars weighted by both"
        if model is None:
            return line
        return f"{line}; {noise_model_text(model, radial_tried=noise_model != 'constant')}"
    return f"noise: {outcome.sigma_estimated_px:.4f} px estimated, {outcome.sigma_px:.4f} px used for sigma"


def _print_report(outcome, out_path: str, time_note: str | None = None, noise_model: str = "auto") -> None:
    from hostlink.api import DISTORTION_NAMES, DISTORTION_UNITS, focal_hint, iterations_text

    sig = outcome.sigma()
    p = outcome.params
    rows = [
        ("f [mm]", p.focal_length_mm, sig["focal_length_mm"]),
        ("x0 [px]", p.principal_point_px[0], sig["principal_point_px"][0]),
        ("y0 [px]", p.principal_point_px[1], sig["principal_point_px"][1]),
    ]
    rows += [(f"{k} [{DISTORTION_UNITS[k]}]", getattr(p.distortion, k), sig["distortion"][k]) for k in DISTORTION_NAMES]
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
        _noise_line(outcome, noise_model)
        + f"; {iterations_text(outcome.history)}{'' if outcome.converged else ' (NOT converged)'}",
    ]
    pre = outcome.prepass
    if pre and abs(pre["focal_scale"] - 1.0) > 0.01:
        ratio = pre["focal_scale"]
        lines_after.insert(
            0,
            f"focal length from the stars: {pre['start_focal_length_mm']:.6g} mm, where the fit started (the nominal "
            f"{pre['nominal_focal_length_mm']:.6g} mm is off by {100 * (1 / ratio - 1):+.1f} %){focal_hint(ratio)}",
        )
    lines_after += [f"held at nominal: {h['parameter']} ({h['reason']})" for h in outcome.held]
    if time_note:
        lines_after.append(time_note)
    lines_after += [f"degeneracy: {m}" for m in outcome.degeneracies["messages"]]
    lines_after.append(f"written: {out_path}")

    held = {h["parameter"] for h in outcome.held}

    def fmt_sigma(name, v):
        if name.split()[0] in held:
            return "held (nominal)"
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
        t.add_row(escape(name), f"{value:.8g}", fmt_sigma(name, s))
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
