"""``hostlink attitude``: the attitude of every frame of a session, as the sensor computes it.

Parses the options, calls :func:`hostlink.sky.attitude.solve_attitudes` (reference directions, diurnal aberration,
refraction modes, ship angles: see that module) and writes ATTITUDE.csv (:mod:`hostlink.files.attitude`).
"""

from __future__ import annotations

import argparse
import math

from hostlink.api import DEFAULT_REJECT_ARCSEC, PRECISIONS, REFRACTION_MODELS, REFRACTION_MODES, UserError
from hostlink.commands.jsonopt import add_json_argument
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
    "R1(roll) R3(pitch) R2(-yaw) from north-up-east to bow-mast-starboard), empty for an unsolved frame. "
    "Every row also has the attitude as a quaternion q0,q1,q2,q3 (scalar first, q0 >= 0: the rotation carrying the "
    "reference axes onto the sensor axes, scipy's Rotation.from_matrix(C.T)) and the boresight's "
    "boresight_ra_deg,boresight_dec_deg and roll_deg (from the image's up, -y, to the projected celestial north, "
    "toward +x; as 'hostlink identify' prints). --wcs DIR writes one FITS header per solved frame, "
    "DIR/frame_<frame>.fits: TAN at the boresight with SIP distortion of the camera (its fit error stated in the "
    "header and printed), for astropy's WCS."
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
    _add_wcs_argument(parser)
    add_json_argument(parser, "the attitudes (frames: one object per row, keyed by ATTITUDE.csv's columns)")


def _add_wcs_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--wcs",
        metavar="DIR",
        help="also write a FITS WCS header per solved frame, DIR/frame_<frame>.fits (TAN-SIP of the calibrated "
        "camera: astropy's WCS(header).all_pix2world(x_px, y_px, 0) gives the stars' directions)",
    )


def _silent(*_args, **_kwargs) -> None:
    """``print`` when --json asks for the object alone on stdout."""


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
    if args.wcs:  # refused before anything is solved or written
        from hostlink.api import wcs_directory

        wcs_directory(args.wcs)
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
    report = print if not args.json else _silent
    report(
        f"hostlink attitude: {attitudes.n_solved}/{attitudes.n_frames} frames solved (refraction: {mode}) -> {args.out}"
    )
    wcs = None
    if args.wcs and attitudes.n_solved:
        from hostlink.api import sip_model, write_wcs_headers

        sip = sip_model(params.model_vector(), params.image_size_px)
        n = write_wcs_headers(args.wcs, attitudes, params, sip, session.time_known, site is not None)
        wcs = {
            "directory": args.wcs,
            "files": n,
            "sip_order": sip.order,
            "sip_error_px": sip.forward_error_px,
            "sip_inverse_order": sip.inverse_order,
            "sip_inverse_error_px": sip.inverse_error_px,
        }
        report(
            f"wcs: {n} FITS headers (TAN-SIP order {sip.order}, error {sip.forward_error_px:.2g} px pixel->sky; "
            f"inverse order {sip.inverse_order}, error {sip.inverse_error_px:.2g} px sky->pixel) -> "
            f"{args.wcs}/frame_<frame>.fits"
        )
    if args.json:
        from hostlink.api import attitude_records
        from hostlink.commands.jsonopt import print_json

        print_json(
            {
                "out": args.out,
                "refraction": mode,
                "n_frames": attitudes.n_frames,
                "n_solved": attitudes.n_solved,
                "wcs": wcs,
                "frames": attitude_records(attitudes),
            }
        )
    if attitudes.n_solved == 0:
        raise UserError(
            f"no frame solved (each frame's reason is in the status column of {args.out}; --min-stars {args.min_stars})"
        )
    return 0
