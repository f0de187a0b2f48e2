"""THE reference-direction service (ARCHITECTURE.md ``hostlink/sky``): the rows of a session -> the unit vector r
of each star at its frame's time, in the true equator and equinox of date, and a note of where they came from.

Every host job that needs reference directions (batch calibration, the onboard estimator's replay, the attitude,
the bench's replay file for a ground sensor) asks :func:`session_references`; none computes them itself.

1. Geocentric apparent place (INTERFACES.md, session file): the file's ``ra_deg, dec_deg`` when it has them;
   otherwise the Hipparcos apparent place of each ``star_id`` at its frame's ``t_utc`` through ERFA
   (:func:`hostlink.sky.apparent.apparent_directions`: pmsafe, apci13, atciq, ra = ri - eo), as the sensor computes
   it from its onboard catalogue. Unidentified rows (``star_id`` 0) have none (NaN).
2. With a ground or ship site: the directions a sensor at that site sees. The site's rotation velocity aberrates
   every star (diurnal aberration, up to 0.32"), then, with weather, refraction lifts it toward the zenith by
   addition (seed 001 sec. 4, the reference-quantity correction): ``onboard.refraction.topocentric_observed`` (one
   formula, one place), per frame, with that frame's zenith and site velocity from ERFA
   (:mod:`hostlink.sky.site`: gst06a and pvtob). A calibration or replay against these references is not biased
   by the atmosphere, however far from the zenith the session looked.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session
from hostlink.sky.catalogue import Catalogue
from onboard.camera import radec_to_unit, unit_to_radec
from onboard.site import Site, Weather

#: ``SessionReferences.source`` values: the session's own columns, or Hipparcos apparent place through ERFA.
SOURCE_FILE = "file"
SOURCE_HIPPARCOS = "hipparcos"


@dataclass(frozen=True)
class SessionReferences:
    """Reference directions of every row of a session, and where they came from.

    r: (N, 3) float64 unit vectors, true equator and equinox of date (topocentric observed with a site); NaN rows
    where :attr:`usable` is False.
    usable: (N,) bool, an identified star (``star_id`` != 0) with a finite reference direction.
    source: ``"file"`` (the session's ra_deg/dec_deg) or ``"hipparcos"`` (apparent place through ERFA).
    refraction: ``"none"`` (geocentric), or a one-line description of the site correction that was applied.
    """

    r: np.ndarray
    usable: np.ndarray
    source: str
    refraction: str = "none"

    @property
    def n_rows(self) -> int:
        return int(self.usable.shape[0])

    @property
    def n_unidentified(self) -> int:
        """Rows without a reference direction (star_id 0): not usable by any job that needs one."""
        return int(self.n_rows - np.count_nonzero(self.usable))


def geocentric_references(session: Session, catalogue: Catalogue | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """(r (N, 3) float64, usable (N,) bool, source) of every row: geocentric apparent unit vectors, true equator and
    equinox of date, from the file's ra_deg/dec_deg [deg] when it has them, else from Hipparcos (``catalogue``,
    default the full bundled one) at each frame's UTC. NaN rows for unidentified stars. An identified star_id
    unknown to Hipparcos is a one-line :class:`UserError`."""
    from hostlink.sky.apparent import apparent_directions, hip_lookup

    n = len(session)
    identified = session.star_id != 0
    r = np.full((n, 3), np.nan)
    if session.ra_deg is not None and session.dec_deg is not None:
        ok = identified & np.isfinite(session.ra_deg) & np.isfinite(session.dec_deg)
        r[ok] = radec_to_unit(np.radians(session.ra_deg[ok]), np.radians(session.dec_deg[ok]))
        return r, ok, SOURCE_FILE
    if np.any(identified):
        if catalogue is None:
            from hostlink.sky.catalogue import load_catalogue

            catalogue = load_catalogue()
        rows = hip_lookup(catalogue, session.star_id[identified])
        jd1, jd2 = session.frame_times_jd()
        frame_of_row = np.repeat(np.arange(jd1.size), np.diff(session.frame_starts))[identified]
        r[identified] = apparent_directions(catalogue, rows, jd1[frame_of_row], jd2[frame_of_row])
    return r, identified.copy(), SOURCE_HIPPARCOS


def topocentric_references(
    r: np.ndarray,
    frame_starts: np.ndarray,
    jd_utc1: np.ndarray,
    jd_utc2: np.ndarray,
    site: Site,
    weather: Weather | None,
    dut1_s: float = 0.0,
) -> np.ndarray:
    """Geocentric apparent unit vectors r (N, 3), grouped by frame (``frame_starts``, (F + 1,)), -> as observed from
    the site at each frame's UTC (two-part Julian dates (F,)): aberrated by the site's rotation velocity and, with
    weather, lifted toward that frame's zenith by the refraction (seed 001 sec. 4,
    ``onboard.refraction.topocentric_observed``, float64). ``dut1_s`` = UT1 - UTC [s]. Rows must be finite."""
    from hostlink.sky.site import site_velocity_true_of_date, zenith_true_of_date
    from onboard.refraction import topocentric_observed

    zenith = zenith_true_of_date(jd_utc1, jd_utc2, site, dut1_s)
    velocity_m_s = site_velocity_true_of_date(jd_utc1, jd_utc2, site, dut1_s)
    out = np.empty_like(r)
    for f in range(frame_starts.shape[0] - 1):
        a, b = int(frame_starts[f]), int(frame_starts[f + 1])
        if b > a:
            out[a:b] = topocentric_observed(r[a:b], zenith[f], velocity_m_s[f], weather)
    return out


def site_correction_text(site: Site, weather: Weather | None) -> str:
    """One line naming the site correction of :func:`topocentric_references` (for reports and result files)."""
    where = f"at {site.lat_deg:g}, {site.lon_deg:g}, {site.height_m:g} m"
    if weather is None:
        return f"reference directions with diurnal aberration only (no weather: no refraction) {where}"
    return (
        f"reference directions with diurnal aberration and refraction (seed 001 sec. 4) for "
        f"{weather.temp_c:g} C, {weather.pressure_hpa:g} hPa {where}"
    )


def session_references(
    session: Session,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    catalogue: Catalogue | None = None,
) -> SessionReferences:
    """The reference direction of every row of ``session`` at its frame's time (module docstring): geocentric
    apparent place, and with ``site`` as observed there (diurnal aberration; with ``weather`` also refraction).
    ``dut1_s`` = UT1 - UTC [s] (the site's orientation). Raises :class:`UserError` for weather without a site and
    for an identified star_id that Hipparcos does not have (when the file has no ra_deg/dec_deg)."""
    if weather is not None and site is None:
        raise UserError("weather without a site: refraction depends on where the sensor is")
    r, usable, source = geocentric_references(session, catalogue)
    if site is None or not np.any(usable):
        return SessionReferences(r, usable, source)
    rows = np.flatnonzero(usable)
    sub = session.select(rows)
    jd1, jd2 = sub.frame_times_jd()
    r[rows] = topocentric_references(r[rows], sub.frame_starts, jd1, jd2, site, weather, dut1_s)
    return SessionReferences(r, usable, source, site_correction_text(site, weather))


def session_with_references(session: Session, references: SessionReferences) -> Session:
    """A copy of ``session`` whose ra_deg/dec_deg [deg] are ``references`` (empty, NaN, where not usable): for
    instance the replay file of a ground sensor, which turns its catalogue directions into observed ones itself."""
    ra_rad, dec_rad = unit_to_radec(np.where(references.usable[:, None], references.r, np.array([1.0, 0.0, 0.0])))
    ra_deg = np.where(references.usable, np.degrees(ra_rad), np.nan)
    dec_deg = np.where(references.usable, np.degrees(dec_rad), np.nan)
    return replace(session.select(np.arange(len(session))), ra_deg=ra_deg, dec_deg=dec_deg)
