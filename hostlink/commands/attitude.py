"""``hostlink attitude``: the attitude of every frame of a session (INTERFACES.md), as the sensor computes it.

For each frame: the measured centroids through the camera model (``onboard.camera.pixels_to_unit``), the reference
directions (the session's ``ra_deg, dec_deg``: geocentric apparent place, true equator and equinox of date; or, when
the file has none, the same computed from Hipparcos), and the attitude C with b = C r (``onboard.attitude``, SVD),
after dropping stars whose residual exceeds ``--reject-arcsec`` (misidentifications).

Diurnal aberration (ground and ship-borne sessions: whenever --site is given, whatever --refraction says): the
site's rotation velocity (``onboard.earth.site_velocity_tod_m_s``, 465 m/s cos(lat)) aberrates every star by up to
0.32"; it is applied to the reference directions, never to the measured ones (it is not refraction), in every mode.

Refraction (ground and ship-borne sessions, needs --site and --weather; seed 001):
- ``reference`` (default with --weather; what the sensor does): rotate the reference vectors into the local
  north-up-east frame (``onboard.earth.local_frame_matrix``), aberrate them by the site velocity and lift each by
  the refraction at its true zenith distance (``onboard.refraction.topocentric_observed``), solve the attitude
  there, rotate back: C = C_g R_ig.
- ``observed`` (seed 001 sec. 3, host-side comparison): the reference vectors aberrated by the site velocity (the
  same function, without weather); each measured vector turned away from the zenith by the refraction at its
  apparent zenith distance (``hostlink.sky.observed_correction``), then solve.
- ``none``: no refraction correction (diurnal aberration still applied with --site).
``--precision float32`` runs every onboard step in float32, as the sensor does.

Ship attitude (seed 001 sec. 3.1, eq. 5-6, 21; needs --site and --mounting): with the sensor's installation angles
(Table 5: yaw, pitch, roll of the sensor in the ship's body frame x bow, y mast, z starboard) as the mounting matrix
R_bs = R1(roll) R3(pitch) R2(-yaw) (``onboard.attitude.euler_matrix``), the sensor attitude in the local frame
R_gs = C R_ig^T gives the ship's R_gb = R_bs^T R_gs and its yaw, pitch, roll (``onboard.attitude.ship_attitude``).
"""

from __future__ import annotations

import argparse
import math

from hostlink.commands.siteopts import add_site_arguments, site_and_weather
from hostlink.errors import UserError

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

REFRACTION_MODES = ("reference", "observed", "none")
#: Default residual above which a star is dropped as misidentified [arcsec]: far above noise (a few arcsec) and
#: uncorrected differential refraction across a field (< 20" at 75 deg), far below a wrong identity (degrees).
DEFAULT_REJECT_ARCSEC = 60.0
OUTPUT_COLUMNS = (
    ("frame", "t_utc", "n_stars", "n_used")
    + tuple(f"c{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
    + (
        "residual_rms_arcsec",
        "status",
    )
)
SHIP_COLUMNS = ("ship_yaw_deg", "ship_pitch_deg", "ship_roll_deg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("session", metavar="SESSION.csv", help="session file (INTERFACES.md)")
    parser.add_argument("--params", required=True, metavar="PARAMS.json", help="camera parameter file")
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
        choices=("atan", "seed001"),
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
        choices=("float64", "float32"),
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


def refraction_mode(requested: str | None, weather) -> str:
    """The effective mode: reference by default with weather, none without; a correction without weather is an
    error."""
    mode = requested or ("reference" if weather is not None else "none")
    if mode != "none" and weather is None:
        raise UserError(f"--refraction {mode} needs --site and --weather (refraction depends on both)")
    return mode


def reference_vectors(session):
    """(N, 3) float64 reference directions (TOD) and a mask of rows that have one (identified stars)."""
    import numpy as np

    from onboard.camera import radec_to_unit

    identified = session.star_id != 0
    if session.ra_deg is not None and session.dec_deg is not None:
        ra, dec = session.ra_deg, session.dec_deg
        usable = identified & np.isfinite(ra) & np.isfinite(dec)
        r = radec_to_unit(np.radians(np.where(usable, ra, 0.0)), np.radians(np.where(usable, dec, 0.0)))
        return r, usable
    from hostlink.files.times import parse_iso_utc_many
    from hostlink.sky.apparent import apparent_directions, hip_lookup
    from hostlink.sky.catalogue import load_catalogue

    r = np.zeros((len(session), 3))
    if np.any(identified):
        cat = load_catalogue()
        rows = hip_lookup(cat, session.star_id[identified])
        jd1, jd2 = parse_iso_utc_many(session.t_utc[identified])
        r[identified] = apparent_directions(cat, rows, jd1, jd2)
    return r, identified


def tai_minus_utc_s(jd1: float, jd2: float) -> int:
    """Leap seconds at a UTC date (ERFA dat), the data a sensor is given with its time."""
    import erfa

    y, m, d, fd = erfa.jd2cal(jd1, jd2)
    return int(round(float(erfa.dat(y, m, d, fd))))


def solve_session(
    session,
    params,
    site=None,
    weather=None,
    dut1_s: float = 0.0,
    mode: str = "none",
    model: str = "atan",
    reject_arcsec: float = DEFAULT_REJECT_ARCSEC,
    min_stars: int = 2,
    dtype="float64",
    mounting_rad: tuple[float, float, float] | None = None,
    diurnal_aberration: bool = True,
):
    """Per-frame attitudes. Returns a dict of columns (numpy arrays, one entry per frame): frame, t_utc, n_stars,
    n_used, C (F, 3, 3; NaN when unsolved), residual_rms_arcsec, status; with a site and ``mounting_rad`` (the
    sensor's (yaw, pitch, roll) in the ship's body frame [rad]) also ship_ypr_deg (F, 3; NaN when unsolved).
    ``diurnal_aberration=False`` leaves the site velocity out (a zero velocity: for reproducing sources that ignore
    it, such as seed 001, and for showing its size; the command always applies it with a site)."""
    import numpy as np

    from hostlink.files.times import fixed_time_from_iso
    from hostlink.sky.observed_correction import attitude_observed_correction, correct_observed
    from onboard import attitude as att
    from onboard.camera import pixels_to_unit
    from onboard.earth import local_frame_matrix, site_velocity_tod_m_s
    from onboard.refraction import topocentric_observed

    dt = np.dtype(dtype)
    theta = params.model_vector(dt)
    r_all, usable = reference_vectors(session)
    jd1, jd2 = session.frame_times_jd()
    lat_rad = math.radians(site.lat_deg) if site is not None else None
    threshold = dt.type(math.radians(reject_arcsec / 3600.0))
    n_frames = session.n_frames
    out = {
        "frame": np.zeros(n_frames, np.int64),
        "t_utc": np.empty(n_frames, dtype=object),
        "n_stars": np.zeros(n_frames, np.int64),
        "n_used": np.zeros(n_frames, np.int64),
        "C": np.full((n_frames, 3, 3), np.nan),
        "residual_rms_arcsec": np.full(n_frames, np.nan),
        "status": np.empty(n_frames, dtype=object),
    }
    ship = site is not None and mounting_rad is not None
    if ship:
        r_bs = att.euler_matrix(*mounting_rad, dtype=dt)
        out["ship_ypr_deg"] = np.full((n_frames, 3), np.nan)
    leap = None
    up = np.array([0.0, 1.0, 0.0], dtype=dt)
    for k, sl in enumerate(session.frame_slices()):
        out["frame"][k] = session.frame[sl.start]
        out["t_utc"][k] = session.t_utc[sl.start]
        rows = np.arange(sl.start, sl.stop)[usable[sl]]
        out["n_stars"][k] = rows.size
        if rows.size < max(min_stars, 2):
            out["status"][k] = "too_few_stars"
            continue
        b = pixels_to_unit(session.x_px[rows].astype(dt), session.y_px[rows].astype(dt), theta)
        r = r_all[rows].astype(dt)
        if site is not None:
            if leap is None:
                leap = tai_minus_utc_s(jd1[k], jd2[k])
            t_k = fixed_time_from_iso(session.t_utc[sl.start])  # not jd1/jd2: see fixed_time_from_iso
            r_ig = local_frame_matrix(t_k, site, dut1_s, leap, dt)
            v_tod = site_velocity_tod_m_s(t_k, site, dut1_s, leap, dt) if diurnal_aberration else np.zeros(3, dt)
        try:
            if mode == "none":
                if site is not None:  # diurnal aberration only: the reference directions as seen from the site
                    r = topocentric_observed(r, r_ig[1], v_tod)
                c, keep = att.attitude_with_rejection(b, r, threshold)
                r_used, b_used = r, b
            else:
                if mode == "reference":
                    r_app = topocentric_observed(r @ r_ig.T, up, r_ig @ v_tod, weather, model, lat_rad)
                    c_g, keep = att.attitude_with_rejection(b, r_app, threshold)
                    c = c_g @ r_ig
                    r_used, b_used = r_app @ r_ig, b
                else:
                    r = topocentric_observed(r, r_ig[1], v_tod)  # diurnal aberration on the reference side
                    c0, _ = att.attitude_with_rejection(b, r, threshold)
                    # reject on corrected vectors: uncorrected differential refraction across a low field exceeds
                    # the threshold and would drop good stars (c0, good to the refraction, a minute of arc, gives
                    # the zenith in sensor axes to well within what the rejection needs)
                    b_c0 = correct_observed(b, c0 @ r_ig[1], weather, model, lat_rad)
                    _, keep = att.attitude_with_rejection(b_c0, r, threshold)
                    c, b_true = attitude_observed_correction(b[keep], r[keep], r_ig[1], weather, model, lat_rad)
                    r_used, b_used = r[keep], b_true
                    keep = np.ones(int(keep.sum()), dtype=bool)
        except att.DegenerateGeometry:
            out["status"][k] = "degenerate"
            continue
        res = att.residuals_rad(b_used[keep], r_used[keep], c).astype(np.float64)
        out["C"][k] = c
        out["n_used"][k] = int(keep.sum())
        out["residual_rms_arcsec"][k] = math.degrees(float(np.sqrt(np.mean(res**2)))) * 3600.0
        out["status"][k] = "ok"
        if ship:  # R_gs = C R_ig^T (b = R_gs r_local), R_gb = R_bs^T R_gs (seed 001 eq. 5-6, 21)
            out["ship_ypr_deg"][k] = np.degrees(np.array(att.ship_attitude(c @ r_ig.T, r_bs), dtype=np.float64))
    return out


def write_attitudes(path: str, cols: dict) -> None:
    """ATTITUDE.csv (INTERFACES.md): frame,t_utc,n_stars,n_used,c11..c33,residual_rms_arcsec,status, then
    ship_yaw_deg,ship_pitch_deg,ship_roll_deg when ``cols`` has ship_ypr_deg."""
    import csv
    import os
    from pathlib import Path

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            ship = cols.get("ship_ypr_deg")
            w.writerow(OUTPUT_COLUMNS + (SHIP_COLUMNS if ship is not None else ()))
            for k in range(cols["frame"].shape[0]):
                c = cols["C"][k].reshape(9)
                ship_cells = [] if ship is None else ["" if not math.isfinite(v) else repr(float(v)) for v in ship[k]]
                w.writerow(
                    [int(cols["frame"][k]), cols["t_utc"][k], int(cols["n_stars"][k]), int(cols["n_used"][k])]
                    + ["" if not math.isfinite(v) else repr(float(v)) for v in c]
                    + [
                        ""
                        if not math.isfinite(cols["residual_rms_arcsec"][k])
                        else f"{cols['residual_rms_arcsec'][k]:.4f}",
                        cols["status"][k],
                    ]
                    + ship_cells
                )
        os.replace(tmp, path)
    except OSError as exc:
        raise UserError(f"{path}: cannot write ({exc.strerror})") from None


def run(args: argparse.Namespace) -> int:
    from hostlink.files.params import load_params
    from hostlink.files.session import check_on_detector, read_session

    site, weather = site_and_weather(args)
    mode = refraction_mode(args.refraction, weather)
    mounting = parse_mounting(args.mounting) if args.mounting is not None else None
    if mounting is not None and site is None:
        raise UserError("--mounting needs --site (the ship attitude is given in the site's north-up-east frame)")
    if not (args.reject_arcsec > 0 and math.isfinite(args.reject_arcsec)):
        raise UserError(f"--reject-arcsec {args.reject_arcsec}: expected a positive number of arcseconds")
    if args.min_stars < 2:
        raise UserError(f"--min-stars {args.min_stars}: an attitude needs at least 2 stars")
    if args.dut1 is not None and not (math.isfinite(args.dut1) and abs(args.dut1) < 1.0):
        raise UserError(f"--dut1 {args.dut1}: UT1 - UTC is always within +-0.9 s")
    session = read_session(args.session)
    params = load_params(args.params)
    if len(session) == 0:
        raise UserError(f"{args.session}: no observations")
    check_on_detector(session, params.image_size_px, args.session, args.params)
    if not (session.star_id != 0).any():
        raise UserError(f"{args.session}: no identified star (every star_id is 0); an attitude needs identified stars")
    cols = solve_session(
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
    write_attitudes(args.out, cols)
    solved = int(sum(s == "ok" for s in cols["status"]))
    print(f"hostlink attitude: {solved}/{len(cols['status'])} frames solved (refraction: {mode}) -> {args.out}")
    if solved == 0:
        raise UserError(
            f"no frame solved (each frame's reason is in the status column of {args.out}; --min-stars {args.min_stars})"
        )
    return 0
