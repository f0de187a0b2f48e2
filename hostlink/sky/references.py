"""THE reference-direction service (docs/architecture.md ``hostlink/sky``): the rows of a session -> the unit vector r
of each star at its frame's time, in the true equator and equinox of date, and a note of where they came from.

Every host job that needs reference directions (batch calibration, the onboard estimator's replay, the attitude,
the bench's replay file for a ground sensor) asks :func:`session_references`; none computes them itself.

1. Geocentric apparent place (docs/file-formats.md, session file): the file's ``ra_deg, dec_deg`` when it has them;
   otherwise the Hipparcos apparent place of each ``star_id`` at its frame's ``t_utc`` through ERFA
   (:func:`hostlink.sky.apparent.apparent_directions`: pmsafe, apci13, atciq, ra = ri - eo), as the sensor computes
   it from its onboard catalogue. Unidentified rows (``star_id`` 0) have none (NaN).
2. With a ground or ship site: the directions a sensor at that site sees. The site's rotation velocity aberrates
   every star (diurnal aberration, up to 0.32"), then, with weather, refraction lifts it toward the zenith by
   addition (seed 001 sec. 4, the reference-quantity correction): ``onboard.refraction.topocentric_observed`` (one
   formula, one place), per frame, with that frame's zenith and site velocity from ERFA
   (:mod:`hostlink.sky.site`: gst06a and pvtob). A calibration or replay against these references is not biased
   by the atmosphere, however far from the zenith the session looked.
3. Time unknown (every ``t_utc`` empty): the file's ``ra_deg, dec_deg`` are taken as J2000 catalogue (ICRS)
   directions, or without them the Hipparcos place at J2000.0 (proper motion applied, ``erfa.pmsafe``). They differ
   from the apparent place of date by precession and nutation (a rotation, which a per-frame attitude absorbs) and by
   annual aberration (up to 20.5", not a rotation: it changes interstar angles by up to 20.5" x the pair's angle in
   radians), so only jobs that work on interstar angles can use them, with that loss (:data:`ABERRATION_MAX_RAD`).

Identified rows whose ``star_id`` Hipparcos does not have (when the file gives no ra/dec) are skipped and named in
:attr:`SessionReferences.unknown`, never fatal.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session
from hostlink.sky.catalogue import Catalogue
from onboard.camera import radec_to_unit
from onboard.site import Site, Weather

#: ``SessionReferences.source`` values: the session's own columns, or Hipparcos apparent place through ERFA; and,
#: with the time unknown, the file's columns as J2000 catalogue directions or Hipparcos at J2000.0.
SOURCE_FILE = "file"
SOURCE_HIPPARCOS = "hipparcos"
SOURCE_FILE_J2000 = "file-j2000"
SOURCE_HIPPARCOS_J2000 = "hipparcos-j2000"
#: Largest annual aberration [rad]: v_earth / c = 29.8 km/s / c = 20.5" (IERS Conventions, the constant of aberration).
ABERRATION_MAX_RAD = 20.49552 / 206264.806


@dataclass(frozen=True)
class SessionReferences:
    """Reference directions of every row of a session, and where they came from.

    r: (N, 3) float64 unit vectors, true equator and equinox of date (topocentric observed with a site); NaN rows
    where :attr:`usable` is False.
    usable: (N,) bool, an identified star (``star_id`` != 0) with a finite reference direction.
    source: ``"file"`` (the session's ra_deg/dec_deg) or ``"hipparcos"`` (apparent place through ERFA); with the
    time unknown ``"file-j2000"`` or ``"hipparcos-j2000"`` (module docstring, item 3).
    refraction: ``"none"`` (geocentric), or a one-line description of the site correction that was applied.
    unknown: (N,) bool, identified rows whose star_id is not in the Hipparcos catalogue (skipped); None: no row.
    """

    r: np.ndarray
    usable: np.ndarray
    source: str
    refraction: str = "none"
    unknown: np.ndarray | None = None

    @property
    def time_known(self) -> bool:
        """False when the directions are J2000 catalogue places (the session gave no time)."""
        return self.source not in (SOURCE_FILE_J2000, SOURCE_HIPPARCOS_J2000)

    @property
    def unknown_rows(self) -> np.ndarray:
        """Session rows (int64) whose star_id Hipparcos does not have."""
        return np.zeros(0, dtype=np.int64) if self.unknown is None else np.flatnonzero(self.unknown)

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
    default the full bundled one) at each frame's UTC; with the time unknown, J2000 catalogue directions (module
    docstring, item 3). NaN rows for unidentified stars and for star_ids Hipparcos does not have (not usable:
    :attr:`SessionReferences.unknown` names them)."""
    from hostlink.sky.apparent import apparent_directions, hip_find, stars_at_j2000

    n = len(session)
    identified = session.star_id != 0
    r = np.full((n, 3), np.nan)
    timed = session.time_known
    if session.ra_deg is not None and session.dec_deg is not None:
        ok = identified & np.isfinite(session.ra_deg) & np.isfinite(session.dec_deg)
        r[ok] = radec_to_unit(np.radians(session.ra_deg[ok]), np.radians(session.dec_deg[ok]))
        return r, ok, SOURCE_FILE if timed else SOURCE_FILE_J2000
    usable = identified.copy()
    if np.any(identified):
        if catalogue is None:
            from hostlink.sky.catalogue import load_catalogue

            catalogue = load_catalogue()
        rows, found = hip_find(catalogue, session.star_id[identified])
        usable[identified] = found
        rows = rows[found]
        if timed:
            jd1, jd2 = session.frame_times_jd()
            frame_of_row = np.repeat(np.arange(jd1.size), np.diff(session.frame_starts))[usable]
            r[usable] = apparent_directions(catalogue, rows, jd1[frame_of_row], jd2[frame_of_row])
        elif rows.size:
            stars = stars_at_j2000(catalogue, rows)
            r[usable] = radec_to_unit(stars.ra_rad, stars.dec_rad)
    return r, usable, SOURCE_HIPPARCOS if timed else SOURCE_HIPPARCOS_J2000


def topocentric_references(
    r: np.ndarray,
    frame_starts: np.ndarray,
    jd_utc1: np.ndarray,
    jd_utc2: np.ndarray,
    site: Site,
    weather: Weather | None,
    dut1_s: float = 0.0,
    precision: str = "float64",
) -> np.ndarray:
    """Geocentric apparent unit vectors r (N, 3), grouped by frame (``frame_starts``, (F + 1,)), -> as observed from
    the site at each frame's UTC (two-part Julian dates (F,)): aberrated by the site's rotation velocity and, with
    weather, lifted toward that frame's zenith by the refraction (seed 001 sec. 4,
    ``onboard.refraction.topocentric_observed``, float64). ``dut1_s`` = UT1 - UTC [s]. Rows must be finite.
    ``precision="fixed"``: as a sensor without an FPU computes it (``topocentric_observed_fixed``, in integers)."""
    from hostlink.sky.site import site_velocity_true_of_date, zenith_true_of_date
    from onboard.refraction import topocentric_observed, topocentric_observed_fixed

    observe = topocentric_observed_fixed if precision == "fixed" else topocentric_observed

    zenith = zenith_true_of_date(jd_utc1, jd_utc2, site, dut1_s)
    velocity_m_s = site_velocity_true_of_date(jd_utc1, jd_utc2, site, dut1_s)
    out = np.empty_like(r)
    for f in range(frame_starts.shape[0] - 1):
        a, b = int(frame_starts[f]), int(frame_starts[f + 1])
        if b > a:
            out[a:b] = observe(r[a:b], zenith[f], velocity_m_s[f], weather)
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
    skip_unknown_ids: bool = False,
    first_row: int = 0,
    precision: str = "float64",
) -> SessionReferences:
    """The reference direction of every row of ``session`` at its frame's time (module docstring): geocentric
    apparent place, and with ``site`` as observed there (diurnal aberration; with ``weather`` also refraction).
    ``dut1_s`` = UT1 - UTC [s] (the site's orientation). Raises :class:`UserError` for weather without a site and
    for a site when the session gives no time. An identified star_id Hipparcos does not have (when the file has no
    ra_deg/dec_deg) is a one-line :class:`UserError`, or with ``skip_unknown_ids`` a row that is not usable and is
    listed in :attr:`SessionReferences.unknown` (batch calibration skips and reports them). ``first_row``: the row
    of the session's first row in the whole session, for that error (a chunk of a session read in chunks). ``precision``
    "fixed": the site correction as a sensor without an FPU computes it (:func:`topocentric_references`)."""
    if weather is not None and site is None:
        raise UserError("weather without a site: refraction depends on where the sensor is")
    if site is not None and not session.time_known:
        raise UserError("--site needs the time of every frame, and the session gives none (t_utc empty)")
    r, usable, source = geocentric_references(session, catalogue)
    unknown = (session.star_id != 0) & ~usable if source in (SOURCE_HIPPARCOS, SOURCE_HIPPARCOS_J2000) else None
    if unknown is not None and not skip_unknown_ids and np.any(unknown):
        k = int(np.argmax(unknown))
        raise UserError(
            f"star_id {int(session.star_id[k])}: not in the Hipparcos catalogue (within its magnitude limit), "
            f"row {first_row + k} (line {first_row + k + 2})"
        )
    if site is None or not np.any(usable):
        return SessionReferences(r, usable, source, unknown=unknown)
    rows = np.flatnonzero(usable)
    sub = session.select(rows)
    jd1, jd2 = sub.frame_times_jd()
    r[rows] = topocentric_references(r[rows], sub.frame_starts, jd1, jd2, site, weather, dut1_s, precision)
    return SessionReferences(r, usable, source, site_correction_text(site, weather), unknown)


def session_with_references(session: Session, references: SessionReferences) -> Session:
    """A copy of ``session`` whose ra_deg/dec_deg [deg] are ``references`` (empty, NaN, where not usable): for
    instance the replay file of a ground sensor, which turns its catalogue directions into observed ones itself."""
    from hostlink.sky.apparent import radec_deg_of_units

    ra_deg, dec_deg = radec_deg_of_units(np.where(references.usable[:, None], references.r, np.array([1.0, 0.0, 0.0])))
    ra_deg = np.where(references.usable, ra_deg, np.nan)
    dec_deg = np.where(references.usable, dec_deg, np.nan)
    return replace(session.select(np.arange(len(session))), ra_deg=ra_deg, dec_deg=dec_deg)
