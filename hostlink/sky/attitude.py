"""The attitude of every frame of a session (docs/file-formats.md), as the sensor computes it: the library behind
``hostlink attitude``.

It lives in ``hostlink/sky`` because it is the sky side of a frame: measured directions matched to the sky's
reference directions (:mod:`hostlink.sky.references`), with the site geometry and the atmosphere
(:mod:`hostlink.sky.observed_correction`) of the same room; the camera enters only through its parameter file.

For each frame: the measured centroids through the camera model (``onboard.camera.pixels_to_unit``), the reference
directions (:func:`hostlink.sky.references.session_references`: the session's ``ra_deg, dec_deg``, or Hipparcos
apparent place when the file has none), and the attitude C with b = C r (``onboard.attitude``, SVD), after dropping
stars whose residual exceeds ``reject_arcsec`` (misidentifications).

Diurnal aberration (ground and ship-borne sessions: whenever a site is given, whatever the refraction mode): the
site's rotation velocity (``onboard.earth.site_velocity_tod_m_s``, 465 m/s cos(lat)) aberrates every star by up to
0.32"; it is applied to the reference directions, never to the measured ones (it is not refraction), in every mode.
The site frame and velocity are the SENSOR's own (``onboard.earth``, in the solve's precision), not ERFA's: this is
the sensor's computation, checked against ERFA's local frame in the tests.

Refraction (ground and ship-borne sessions, needs a site and weather; seed 001):
- ``reference`` (default with weather; what the sensor does): rotate the reference vectors into the local
  north-up-east frame (``onboard.earth.local_frame_matrix``), aberrate them by the site velocity and lift each by
  the refraction at its true zenith distance (``onboard.refraction.topocentric_observed``), solve the attitude
  there, rotate back: C = C_g R_ig.
- ``observed`` (seed 001 sec. 3, host-side comparison): the reference vectors aberrated by the site velocity (the
  same function, without weather); each measured vector turned away from the zenith by the refraction at its
  apparent zenith distance (``hostlink.sky.observed_correction``), then solve.
- ``none``: no refraction correction (diurnal aberration still applied with a site).
``dtype="float32"`` runs every onboard step in float32, as the sensor does.

Ship attitude (seed 001 sec. 3.1, eq. 5-6, 21; needs a site and the mounting): with the sensor's installation angles
(Table 5: yaw, pitch, roll of the sensor in the ship's body frame x bow, y mast, z starboard) as the mounting matrix
R_bs = R1(roll) R3(pitch) R2(-yaw) (``onboard.attitude.euler_matrix``), the sensor attitude in the local frame
R_gs = C R_ig^T gives the ship's R_gb = R_bs^T R_gs and its yaw, pitch, roll (``onboard.attitude.ship_attitude``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session, check_on_detector
from hostlink.files.times import fixed_time_from_iso, tai_minus_utc_s
from hostlink.sky.attitude_choices import DEFAULT_REJECT_ARCSEC, PRECISIONS, REFRACTION_MODELS, REFRACTION_MODES
from hostlink.sky.observed_correction import attitude_observed_correction, correct_observed
from hostlink.sky.references import session_references
from onboard import attitude as att
from onboard.camera import pixels_to_unit
from onboard.earth import local_frame_matrix, site_velocity_tod_m_s
from onboard.params import CameraParams
from onboard.refraction import topocentric_observed
from onboard.site import Site, Weather

#: Frame status values: solved, fewer usable stars than ``min_stars``, or stars in a degenerate geometry.
STATUS_OK, STATUS_TOO_FEW, STATUS_DEGENERATE = "ok", "too_few_stars", "degenerate"


@dataclass(frozen=True)
class SessionAttitudes:
    """The attitude of each of F frames. ``C`` (F, 3, 3) maps the true equator and equinox of date to sensor axes
    (b = C r), NaN when unsolved; ``residual_rms_arcsec`` (F,) of the stars used, NaN when unsolved; ``status`` (F,)
    one of ``ok``, ``too_few_stars``, ``degenerate``; ``ship_ypr_deg`` (F, 3) the ship's yaw, pitch, roll [deg] in
    the local north-up-east frame (NaN when unsolved), only with a site and a mounting; ``mode`` the refraction
    correction applied."""

    frame: np.ndarray
    t_utc: np.ndarray
    n_stars: np.ndarray
    n_used: np.ndarray
    C: np.ndarray
    residual_rms_arcsec: np.ndarray
    status: np.ndarray
    mode: str
    ship_ypr_deg: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.frame.shape[0])

    @property
    def n_solved(self) -> int:
        return int(np.count_nonzero(self.status == STATUS_OK))


def refraction_mode(requested: str | None, weather: Weather | None) -> str:
    """The effective refraction mode: ``requested``, or by default ``reference`` with weather and ``none`` without.
    A correction without weather, or an unknown mode, is a one-line :class:`UserError`."""
    mode = requested or ("reference" if weather is not None else "none")
    if mode not in REFRACTION_MODES:
        raise UserError(f"--refraction {mode!r}: expected one of {', '.join(REFRACTION_MODES)}")
    if mode != "none" and weather is None:
        raise UserError(f"--refraction {mode} needs --site and --weather (refraction depends on both)")
    return mode


def _check_options(
    site: Site | None,
    weather: Weather | None,
    mode: str,
    model: str,
    reject_arcsec: float,
    min_stars: int,
    dtype: str,
    mounting_rad: tuple[float, float, float] | None,
) -> None:
    if weather is not None and site is None:
        raise UserError("--weather needs --site (refraction depends on where the sensor is)")
    refraction_mode(mode, weather)
    if model not in REFRACTION_MODELS:
        raise UserError(f"--refraction-model {model!r}: expected one of {', '.join(REFRACTION_MODELS)}")
    if not (reject_arcsec > 0 and math.isfinite(reject_arcsec)):
        raise UserError(f"--reject-arcsec {reject_arcsec}: expected a positive number of arcseconds")
    if min_stars < 2:
        raise UserError(f"--min-stars {min_stars}: an attitude needs at least 2 stars")
    if str(np.dtype(dtype)) not in PRECISIONS:
        raise UserError(f"--precision {dtype}: expected one of {', '.join(PRECISIONS)}")
    if mounting_rad is not None:
        if site is None:
            raise UserError("--mounting needs --site (the ship attitude is given in the site's north-up-east frame)")
        if len(mounting_rad) != 3 or not all(math.isfinite(a) for a in mounting_rad):
            raise UserError(f"--mounting {mounting_rad}: expected 3 finite angles")


def _solve_frame(b, r, r_ig, v_tod, mode, weather, model, lat_rad, threshold):
    """One frame's attitude: (C, keep mask over the stars used, the reference and measured vectors used)."""
    if r_ig is None:  # no site: geocentric references as they are
        c, keep = att.attitude_with_rejection(b, r, threshold)
        return c, keep, r, b
    zenith = r_ig[1]
    if mode == "none":  # diurnal aberration only: the reference directions as seen from the site
        r = topocentric_observed(r, zenith, v_tod)
        c, keep = att.attitude_with_rejection(b, r, threshold)
        return c, keep, r, b
    if mode == "reference":
        up = np.array([0.0, 1.0, 0.0], dtype=r.dtype)
        r_app = topocentric_observed(r @ r_ig.T, up, r_ig @ v_tod, weather, model, lat_rad)
        c_g, keep = att.attitude_with_rejection(b, r_app, threshold)
        return c_g @ r_ig, keep, r_app @ r_ig, b
    r = topocentric_observed(r, zenith, v_tod)  # diurnal aberration on the reference side
    c0, _ = att.attitude_with_rejection(b, r, threshold)
    # reject on corrected vectors: uncorrected differential refraction across a low field exceeds the threshold and
    # would drop good stars (c0, good to the refraction, a minute of arc, gives the zenith in sensor axes to well
    # within what the rejection needs)
    b_c0 = correct_observed(b, c0 @ zenith, weather, model, lat_rad)
    _, keep = att.attitude_with_rejection(b_c0, r, threshold)
    c, b_true = attitude_observed_correction(b[keep], r[keep], zenith, weather, model, lat_rad)
    return c, np.ones(int(keep.sum()), dtype=bool), r[keep], b_true


def solve_attitudes(
    session: Session,
    params: CameraParams,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    mode: str = "none",
    model: str = "atan",
    reject_arcsec: float = DEFAULT_REJECT_ARCSEC,
    min_stars: int = 2,
    dtype: str = "float64",
    mounting_rad: tuple[float, float, float] | None = None,
    diurnal_aberration: bool = True,
) -> SessionAttitudes:
    """The attitude of every frame of ``session`` through the camera ``params`` (module docstring).

    ``site``/``weather``: ground or ship site and its weather; ``dut1_s`` = UT1 - UTC [s]; ``mode``: refraction
    correction (``reference``, ``observed``, ``none``), ``model``: ``atan`` (A tan z + B tan^3 z) or ``seed001``;
    ``reject_arcsec``: residual above which a star is dropped [arcsec]; ``min_stars``: fewest usable stars for an
    attitude; ``dtype``: ``float64`` or ``float32`` (the sensor); ``mounting_rad``: the sensor's (yaw, pitch, roll) in
    the ship's body frame [rad], giving ``ship_ypr_deg``. ``diurnal_aberration=False`` leaves the site velocity out
    (a zero velocity: for reproducing sources that ignore it, such as seed 001, and for showing its size).

    Raises :class:`UserError` (one line) for inconsistent options, a centroid off the camera's detector, a session
    without an identified star, or a star_id unknown to Hipparcos when the file has no ra_deg/dec_deg. Frames that
    cannot be solved are reported in ``status``, not raised.
    """
    _check_options(site, weather, mode, model, reject_arcsec, min_stars, dtype, mounting_rad)
    check_on_detector(session, params.image_size_px, "the session", "the camera parameters")
    if not np.any(session.star_id != 0):
        raise UserError("no identified star in the session (every star_id is 0); an attitude needs identified stars")
    dt = np.dtype(dtype)
    theta = params.model_vector(dt)
    refs = session_references(session)  # geocentric: the site correction below is the sensor's own
    jd1, jd2 = session.frame_times_jd()
    lat_rad = math.radians(site.lat_deg) if site is not None else None
    threshold = dt.type(math.radians(reject_arcsec / 3600.0))
    n_frames = session.n_frames
    frame = np.zeros(n_frames, np.int64)
    t_utc = np.empty(n_frames, dtype=object)
    n_stars = np.zeros(n_frames, np.int64)
    n_used = np.zeros(n_frames, np.int64)
    c_all = np.full((n_frames, 3, 3), np.nan)
    rms_arcsec = np.full(n_frames, np.nan)
    status = np.empty(n_frames, dtype=object)
    ship = mounting_rad is not None
    ship_ypr_deg = np.full((n_frames, 3), np.nan) if ship else None
    r_bs = att.euler_matrix(*mounting_rad, dtype=dt) if ship else None
    leap_s = tai_minus_utc_s(jd1[0], jd2[0]) if site is not None and n_frames else None
    r_ig = v_tod = None
    for k, sl in enumerate(session.frame_slices()):
        frame[k] = session.frame[sl.start]
        t_utc[k] = session.t_utc[sl.start]
        rows = np.arange(sl.start, sl.stop)[refs.usable[sl]]
        n_stars[k] = rows.size
        if rows.size < max(min_stars, 2):
            status[k] = STATUS_TOO_FEW
            continue
        b = pixels_to_unit(session.x_px[rows].astype(dt), session.y_px[rows].astype(dt), theta)
        r = refs.r[rows].astype(dt)
        if site is not None:
            t_k = fixed_time_from_iso(session.t_utc[sl.start])  # not jd1/jd2: see fixed_time_from_iso
            r_ig = local_frame_matrix(t_k, site, dut1_s, leap_s, dt)
            v_tod = site_velocity_tod_m_s(t_k, site, dut1_s, leap_s, dt) if diurnal_aberration else np.zeros(3, dt)
        try:
            c, keep, r_used, b_used = _solve_frame(b, r, r_ig, v_tod, mode, weather, model, lat_rad, threshold)
        except att.DegenerateGeometry:
            status[k] = STATUS_DEGENERATE
            continue
        res = att.residuals_rad(b_used[keep], r_used[keep], c).astype(np.float64)
        c_all[k] = c
        n_used[k] = int(keep.sum())
        rms_arcsec[k] = math.degrees(float(np.sqrt(np.mean(res**2)))) * 3600.0
        status[k] = STATUS_OK
        if ship:  # R_gs = C R_ig^T (b = R_gs r_local), R_gb = R_bs^T R_gs (seed 001 eq. 5-6, 21)
            ship_ypr_deg[k] = np.degrees(np.array(att.ship_attitude(c @ r_ig.T, r_bs), dtype=np.float64))
    return SessionAttitudes(frame, t_utc, n_stars, n_used, c_all, rms_arcsec, status, mode, ship_ypr_deg)
