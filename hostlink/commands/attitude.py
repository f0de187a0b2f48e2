"""``hostlink attitude``: the attitude of every frame of a session, as the sensor computes it.

Parses the options, calls :func:`hostlink.sky.attitude.solve_attitudes` (reference directions, diurnal aberration,
refraction modes, ship angles: see that module) and writes ATTITUDE.csv (:mod:`hostlink.files.attitude`).
"""

from __future__ import annotations

import argparse
import math

from hostlink.api import DEFAULT_REJECT_ARCSEC, PRECISIONS, REFRACTION_MODELS, REFRACTION_MODES, UserError
from hostlink.commands.siteopts import add_site_arguments, site_and_weather

HELP = "attitude per frame (b = C r) from a session, with refraction correction for ground sessions"
DESCRIPTION = (
    "Compute the attitude C (b = C r, r the geocentric apparent place in the true equator and equinox of date) of "
    "every frame of SESSION.csv through the camera PARAMS.json. With --site and --weather the stars' atmospheric "
    "refraction is corrected: 'reference' lifts the reference directions toward the zenith (seed 001 sec. 4, the "
    "sensor's method, default), 'observed' lowers the measured ones (seed 001 sec. 3), 'none' skips it. With "
    "--site the reference directions always get the diurnal aberration of the site's rotation (up to 0.32\"), "
    "whatever --refraction says: a ground sensor sees topocentric directions. Writes "
    "ATTITUDE.csv with frame,t_utc,n_stars,n_used,c11..c33,residual_rms_arcsec,status; with --site and --mounting "
    "also ship_yaw_deg,ship_pitch_deg,ship_roll_deg: the ship's attitude in the local north-up-east frame (seed 001: "
    "yaw from north toward east in [0, 360), pitch bow up in [-90, 90], roll starboard down in (-180, 180], the "
    "frame rotation "
    "R1(roll) R3(pitch) R2(-yaw) from north-up-east to bow-mast-starboard), empty for an unsolved frame."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION.csv", help="session file (docs/file-formats.md)")
    parser.add_argument(
        "--params",
        required=True,
        metavar="PARAMS.json",
        help="camera parameter file"
        " (a path, or builtin:NAME for one shipped with the package, e.g. builtin:seed004_camera)",
    )
    parser.add_argument("--out", required=True, metavar="ATTITUDE.csv", help="attitude file to write")
    add_site_arguments(parser)
    parser.add_argument(
        "--refraction",
        choices=REFRACTION_MODES,
        help="refraction correction: reference (default with --weather), observed, or none (default without); "
        "with --site, diurnal aberration is applied to the reference directions in every mode",
    )
    parser.add_argument(
        "--refraction-model",
        choices=REFRACTION_MODELS,
        default="atan",
        help='atan: A tan z + B tan^3 z from T, P, RH, wavelength (default); seed001: 60.2" tan z (1 + M + N)',
    )
    parser.add_argument(
        "--reject-arcsec",
        type=float,
        default=DEFAULT_REJECT_ARCSEC,
        metavar="ARCSEC",
        help=f"drop stars with a larger residual (default {DEFAULT_REJECT_ARCSEC:g})",
    )
    parser.add_argument(
        "--min-stars", type=int, default=2, metavar="K", help="fewest identified stars for an attitude (default 2)"
    )
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="float64",
        help="arithmetic of the onboard steps (float32: as the sensor)",
    )
    parser.add_argument(
        "--mounting",
        metavar="YAW_DEG,PITCH_DEG,ROLL_DEG",
        help="the sensor's installation angles in the ship's body frame (x bow, y mast, z starboard; seed 001 "
        "Table 5, frame rotation R1(roll) R3(pitch) R2(-yaw)); with --site, adds the columns ship_yaw_deg, "
        "ship_pitch_deg, ship_roll_deg (ship attitude in the local north-up-east frame, yaw from north toward "
        "east)",
    )


def parse_mounting(text: str) -> tuple[float, float, float]:
    """``YAW_DEG,PITCH_DEG,ROLL_DEG`` -> (yaw, pitch, roll) [rad]; any finite angles (Table 5 has a pitch of 180.2)."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise UserError(f"--mounting {text!r}: expected 3 finite angles in degrees, e.g. 91.5,180.2,39.5")
    return tuple(math.radians(v) for v in values)


def run(args: argparse.Namespace) -> int:
    from hostlink.api import (
        check_on_detector,
        load_params,
        read_session,
        refraction_mode,
        solve_attitudes,
        write_attitudes,
    )

    site, weather = site_and_weather(args)
    mode = refraction_mode(args.refraction, weather)
    mounting = parse_mounting(args.mounting) if args.mounting is not None else None
    session = read_session(args.session)
    params = load_params(args.params)
    if len(session) == 0:
        raise UserError(f"{args.session}: no observations")
    check_on_detector(session, params.image_size_px, args.session, args.params)
    attitudes = solve_attitudes(
        session,
        params,
        site,
        weather,
        args.dut1 or 0.0,
        mode,
        args.refraction_model,
        args.reject_arcsec,
        args.min_stars,
        args.precision,
        mounting,
    )
    write_attitudes(args.out, attitudes)
    print(
        f"hostlink attitude: {attitudes.n_solved}/{attitudes.n_frames} frames solved (refraction: {mode}) -> {args.out}"
    )
    if attitudes.n_solved == 0:
        raise UserError(
            f"no frame solved (each frame's reason is in the status column of {args.out}; --min-stars {args.min_stars})"
        )
    return 0
