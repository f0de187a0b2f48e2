"""Reference directions for a calibration session (INTERFACES.md, session file).

- From the file's ``ra_deg, dec_deg`` (geocentric apparent place, true equator and equinox of date) when present;
  otherwise from Hipparcos as apparent place at each frame's ``t_utc`` (``hostlink.sky.apparent``, pyerfa).
- Ground sessions (``--site``): the stars were seen from a rotating site (diurnal aberration, <= 0.32") and, with
  ``--weather``, through the atmosphere, lifted toward the zenith. The reference directions are turned the same
  way before the fit (seed 001 sec. 4, the reference-quantity correction, preceded by the site-velocity
  aberration), so a calibration made far from the zenith is not biased. The formula lives in
  ``onboard.refraction.topocentric_observed`` (one formula, one place); the zenith and the site velocity of date
  come from ``hostlink.sky.site`` (ERFA).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData, build_data
from hostlink.errors import UserError
from hostlink.files.session import Session
from onboard.camera import radec_to_unit
from onboard.site import Site, Weather


@dataclass(frozen=True)
class ReferenceInfo:
    source: str  # "file" or "hipparcos"
    refraction: str  # "none" or a description
    n_unidentified: int  # rows with star_id 0 (not usable)
    n_rows: int


def reference_directions(session: Session, rows: np.ndarray, dut1_s: float = 0.0) -> tuple[np.ndarray, str]:
    """(len(rows), 3) apparent unit vectors of the given session rows, and where they came from."""
    if session.ra_deg is not None and session.dec_deg is not None:
        return radec_to_unit(np.radians(session.ra_deg[rows]), np.radians(session.dec_deg[rows])), "file"
    from hostlink.sky.apparent import apparent_directions, hip_lookup
    from hostlink.sky.catalogue import load_catalogue

    cat = load_catalogue()
    cat_rows = hip_lookup(cat, session.star_id[rows])
    sub = session.select(rows)
    jd1_f, jd2_f = sub.frame_times_jd()
    counts = np.diff(sub.frame_starts)
    jd1, jd2 = np.repeat(jd1_f, counts), np.repeat(jd2_f, counts)
    return apparent_directions(cat, cat_rows, jd1, jd2, dut1_s), "hipparcos"


def refract_references(
    r: np.ndarray,
    frame_starts: np.ndarray,
    jd1: np.ndarray,
    jd2: np.ndarray,
    site: Site,
    weather: Weather | None,
    dut1_s: float = 0.0,
) -> np.ndarray:
    """Each frame's geocentric apparent reference directions as observed from the site: aberrated by the site's
    rotation velocity (diurnal aberration) and, with weather, lifted toward that frame's zenith by the refraction
    (seed 001 sec. 4): ``onboard.refraction.topocentric_observed``, in float64, per frame."""
    from hostlink.sky.site import site_velocity_true_of_date, zenith_true_of_date
    from onboard.refraction import topocentric_observed

    zenith = zenith_true_of_date(jd1, jd2, site, dut1_s)
    velocity = site_velocity_true_of_date(jd1, jd2, site, dut1_s)
    out = np.empty_like(r)
    for f in range(frame_starts.shape[0] - 1):
        a, b = int(frame_starts[f]), int(frame_starts[f + 1])
        out[a:b] = topocentric_observed(r[a:b], zenith[f], velocity[f], weather)
    return out


def calibration_data_from_session(
    session: Session, site: Site | None = None, weather: Weather | None = None, dut1_s: float = 0.0
) -> tuple[CalibrationData, ReferenceInfo]:
    """The identified rows of a session as :class:`CalibrationData` (frames with >= 3 identified stars)."""
    identified = np.flatnonzero(session.star_id != 0)
    n_unidentified = len(session) - identified.size
    if identified.size == 0:
        raise UserError("the session has no identified star (every star_id is 0)")
    r, source = reference_directions(session, identified, dut1_s)
    sub = session.select(identified)
    data = build_data(sub.x_px, sub.y_px, r, sub.frame, None, sub.star_id)
    refraction = "none"
    if site is not None:
        jd1, jd2 = sub.frame_times_jd()
        r_obs = refract_references(data.r, data.frame_starts, jd1, jd2, site, weather, dut1_s)
        data = build_data(sub.x_px, sub.y_px, r_obs, sub.frame, None, sub.star_id)
        where = f"at {site.lat_deg:g}, {site.lon_deg:g}, {site.height_m:g} m"
        if weather is None:
            refraction = f"reference directions with diurnal aberration only (no weather: no refraction) {where}"
        else:
            refraction = (
                f"reference directions with diurnal aberration and refraction (seed 001 sec. 4) for "
                f"{weather.temp_c:g} C, {weather.pressure_hpa:g} hPa {where}"
            )
    data, _, _ = data.select(np.ones(data.n_obs, dtype=bool))
    if data.n_frames == 0:
        raise UserError("no frame has at least 3 identified stars")
    return data, ReferenceInfo(source, refraction, int(n_unidentified), len(session))
