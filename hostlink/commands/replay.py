"""``hostlink replay``: the onboard recursive calibration over a session, frame by frame, as the sensor runs it."""

from __future__ import annotations

import argparse

from hostlink.commands.jsonopt import add_json_argument

HELP = "run the onboard recursive calibration over a session, exactly as the sensor would"
#: Frames read at a time: the replay's memory is one chunk and the estimator, whatever the session's length.
REPLAY_CHUNK_FRAMES = 2000
DESCRIPTION = (
    "Feeds every frame of SESSION (identified stars; reference directions from its ra_deg/dec_deg or Hipparcos) "
    "to the onboard recursive estimator "
    "(interstar difference measurements, whitened over 2n-3 pairs, Bierman U-D updates, misidentification gating, "
    "focal-drift tracking) starting from NOMINAL.json, and writes the final estimate as a camera parameter file "
    "with a 'sigma' object. --precision float64 runs the same code as the host reference; --precision fixed runs "
    "the per-star front end (camera model, unit vectors, interstar residuals) in integer arithmetic as a sensor "
    "without an FPU would (centroids in the wire's 2^-10 px, unit vectors in Q30, residuals in Q61; "
    "onboard/fixedpoint.py), with the filter update in float32 (soft float on such a sensor). When NOMINAL.json has a "
    "'sigma' object (a calibration result), the estimator starts from it as its prior, exactly as the sensor does "
    "after an upload (parameters without a positive sigma start from the cold-start prior; no burn-in when every "
    "estimated parameter has one); --prior cold ignores it."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "session",
        nargs="+",
        metavar="SESSION",
        help="session file (CSV, or Parquet: SESSION.parquet); several files or a quoted glob pattern "
        "('nights/*.csv') form one session, taken in time order; read in chunks, in bounded memory",
    )
    p.add_argument(
        "--nominal",
        required=True,
        metavar="NOMINAL.json",
        help="starting camera parameters (a path, or builtin:NAME for one shipped with the package, e.g. "
        "builtin:seed004_nominal)",
    )
    p.add_argument("--out", required=True, metavar="ESTIMATE.json", help="where to write the estimate")
    p.add_argument("--trace", metavar="TRACE.csv", help="per-frame trace (frame, focal_length_mm, x0_px, y0_px, ...)")
    p.add_argument(
        "--precision",
        default="float32",
        help="float32 (the sensor, default), float64 (host reference) or fixed (integer front end for a sensor "
        "without an FPU: Q30 unit vectors, Q61 residuals; float32 filter update)",
    )
    p.add_argument(
        "--firmware",
        default="python",
        choices=("python", "c"),
        help="which firmware runs the estimator: python (the reference model, default) or c (the C firmware core, "
        "onboard/c, built once with the machine's C compiler; float32 and fixed)",
    )
    p.add_argument(
        "--estimate",
        metavar="NAMES",
        help="comma-separated parameters to estimate (default all: f,x0,y0,k1,k2,k3,p1,p2,s1,s2)",
    )
    p.add_argument("--noise-px", type=float, default=0.05, help="1-sigma centroid noise per axis [px] (default 0.05)")
    p.add_argument(
        "--focal-walk-um",
        type=float,
        default=0.0,
        help="focal-length random walk per frame, 1-sigma [um] (default 0: static, with automatic drift detection)",
    )
    p.add_argument("--no-drift-detect", action="store_true", help="never switch on the focal random walk by itself")
    p.add_argument("--max-stars", type=int, default=32, help="stars used per frame at most (default 32)")
    p.add_argument(
        "--prior",
        choices=("file", "cold"),
        help="estimator prior: 'file' = the nominal file's sigma (default when the file has one), 'cold' = the "
        "cold-start prior (3%% of f, 5%% of the image side for the principal point, 5 px of distortion)",
    )
    add_json_argument(p, "the estimate (ESTIMATE.json's object)")


def run(args: argparse.Namespace) -> int:
    from contextlib import nullcontext

    from hostlink.api import (
        TraceWriter,
        UserError,
        check_on_detector,
        estimate_extras,
        load_params_with_sigma,
        parse_estimate_names,
        precision_dtype,
        progress_bar,
        read_session_chunks,
        replay_chunks,
        replay_config,
        replay_prior,
        save_params,
        session_paths,
    )

    precision_dtype(args.precision)  # refuse an unknown precision before reading files
    try:
        names = parse_estimate_names(args.estimate)
    except ValueError as exc:
        raise UserError(f"--estimate: {exc}") from None
    replay_config(args.noise_px, args.focal_walk_um, not args.no_drift_detect, args.max_stars)  # checks first
    nominal, file_sigma = load_params_with_sigma(args.nominal)
    config = replay_config(
        args.noise_px, args.focal_walk_um, not args.no_drift_detect, args.max_stars, nominal.focal_length_mm
    )
    prior_sigma = replay_prior(file_sigma, args.prior, args.nominal)
    source = args.session[0] if len(args.session) == 1 else args.session
    name = ", ".join(args.session)
    session_paths(source)  # a pattern that matches nothing is refused before any output is opened

    def chunks():
        for chunk in read_session_chunks(source, REPLAY_CHUNK_FRAMES):
            check_on_detector(chunk, nominal.image_size_px, name, args.nominal)
            yield chunk

    # the session is read, replayed and its trace written chunk by chunk: memory does not grow with the file
    with (
        TraceWriter(args.trace) if args.trace else nullcontext() as trace,
        progress_bar("replaying frames", None) as advance,
    ):
        result = replay_chunks(
            chunks(),
            nominal,
            names,
            config,
            args.precision,
            on_frame=lambda k, _res: advance(k + 1),
            prior_sigma=prior_sigma,
            on_trace=None if trace is None else trace.append,
            name=name,
            firmware_core=args.firmware,
        )
    extras = estimate_extras(result, args.precision)
    save_params(args.out, result.params, extras)
    if args.json:
        from hostlink.api import params_json
        from hostlink.commands.jsonopt import print_json

        print_json(params_json(result.params, extras))
        return 0
    p = result.params
    print(
        f"replayed {result.n_frames} frames ({result.state.updates} used): f = {p.focal_length_mm:.6f} mm, "
        f"principal point ({p.principal_point_px[0]:.3f}, {p.principal_point_px[1]:.3f}) px, prior "
        f"{result.prior} -> {args.out}"
    )
    if extras["status"] != "converged":
        print(f"not converged: {extras['status_reason']} (status {extras['status']}: upload refuses this file)")
    return 0
