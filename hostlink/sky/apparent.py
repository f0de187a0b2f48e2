"""Geocentric apparent place of Hipparcos stars, true equator and equinox of date (seed 000 sec. 3; the session
file's ``ra_deg, dec_deg``, docs/file-formats.md).

The chain, all in pyerfa (IAU 2006/2000A):

1. ``erfa.pmsafe``: space motion from the catalogue epoch J1991.25 to J2000.0 (TT), because ``atci13``/``atciq``
   take J2000 star data (ERFA atci13 note 1). Hipparcos' mu_alpha* is divided by cos(dec) (atci13 note 2).
2. ``erfa.apci13`` once per frame time, then ``erfa.atciq`` per star: proper motion to the date, parallax, light
   deflection by the Sun, annual aberration, and frame bias-precession-nutation to CIRS (seed 000 eq. 15-18 carry
   the same physics in the classical form).
3. Equinox-based right ascension ``ra = ri - eo``, with ``eo = ERA - GST`` the equation of the origins returned by
   ``apci13`` (ERFA atci13 note 5): this moves CIRS onto the true equator and equinox of date.

Times: the frame's UTC is converted to TT (``hostlink.files.times.utc_to_tt``) and used where ERFA asks for TDB;
TDB - TT is below 2 ms, whose effect on aberration is below 1e-9 arcsec. UT1 does not enter a geocentric apparent place.

Per epoch, not per star: ``apci13`` evaluates the whole IAU 2000A nutation series and ``pmsafe``/``atciq`` are
per star, so a session of 10^5 frames of 20 stars would spend minutes on them row by row (their costs:
docs/api.md, "Per epoch, not per star"). :func:`apparent_directions` therefore computes each distinct star's place
exactly at nodes :data:`APPARENT_NODE_SPACING_S` apart (one ``apci13`` per node, one ``atciq`` per star and node)
and interpolates linearly in time between the two nodes around each row's time, then renormalises. The error of linear
interpolation is at most h^2/8 max|d^2 r/dt^2| (h the spacing). The apparent place's fastest curvature comes from
the short-period nutation terms (the 13.66-day term's 0.23" gives 0.049"/day^2, all terms with periods under a
month together less than 0.1"/day^2) and from annual aberration (20.5" (2 pi/year)^2 = 0.006"/day^2); proper
motion and precession are linear to far better than that. At h = 1 h the bound is
0.11"/day^2 x (1/24 day)^2 / 8 = 2.4e-5", 40 times below the 0.001" the project promises;
``tests/test_sky_apparent.py`` measures the interpolated place against ERFA's ``atci13`` star by star.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import erfa
import numpy as np

from hostlink.errors import UserError
from hostlink.files.times import utc_to_tt
from hostlink.sky.catalogue import HIPPARCOS_EPOCH_JD_TT, Catalogue
from onboard.camera import radec_to_unit

_MAS_TO_RAD = np.pi / (180.0 * 3600.0 * 1000.0)
_J2000_JD_TT = 2451545.0


@dataclass(frozen=True)
class StarsJ2000:
    """Star data at epoch J2000.0 in the form ERFA's atciq takes: ICRS ra/dec [rad], dRA/dt and dDec/dt [rad/yr]
    (dRA/dt is NOT multiplied by cos dec), parallax [arcsec], radial velocity [km/s] (0: Hipparcos has none)."""

    ra_rad: np.ndarray
    dec_rad: np.ndarray
    pmra_radyr: np.ndarray
    pmdec_radyr: np.ndarray
    plx_arcsec: np.ndarray
    rv_kms: np.ndarray

    def take(self, rows: np.ndarray) -> StarsJ2000:
        return StarsJ2000(*(getattr(self, k)[rows] for k in self.__dataclass_fields__))


def stars_at_j2000(cat: Catalogue, rows: np.ndarray | None = None) -> StarsJ2000:
    """Propagate catalogue rows (all when None) from J1991.25 to J2000.0 with ``erfa.pmsafe``.

    Non-positive parallaxes are overridden by pmsafe with a safe small value (its note 6; the effect on direction is
    below 1e-9 arcsec); that status warning is silenced here on purpose.
    """
    sel = slice(None) if rows is None else np.asarray(rows)
    dec = cat.dec_rad[sel]
    pmr = cat.pmra_masyr[sel] * _MAS_TO_RAD / np.cos(dec)
    pmd = cat.pmdec_masyr[sel] * _MAS_TO_RAD
    px = np.maximum(cat.plx_mas[sel], 0.0) / 1000.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        ra2, dec2, pmr2, pmd2, px2, rv2 = erfa.pmsafe(
            cat.ra_rad[sel], dec, pmr, pmd, px, 0.0, HIPPARCOS_EPOCH_JD_TT, 0.0, _J2000_JD_TT, 0.0
        )
    return StarsJ2000(*(np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (ra2, dec2, pmr2, pmd2, px2, rv2)))


def frame_astrometry(jd_utc1: np.ndarray, jd_utc2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ERFA star-independent astrometry parameters (``apci13``) and equation of the origins [rad] per UTC time."""
    tt1, tt2 = utc_to_tt(np.atleast_1d(jd_utc1), np.atleast_1d(jd_utc2))
    astrom, eo = erfa.apci13(tt1, tt2)
    return np.atleast_1d(astrom), np.atleast_1d(eo)


def apparent_from_astrometry(stars: StarsJ2000, astrom: np.ndarray, eo_rad: np.ndarray) -> np.ndarray:
    """Apparent directions (N, 3), true equator and equinox of date, of ``stars`` (N entries) with per-star
    ``astrom``/``eo_rad`` (N entries, or one for all): ``atciq`` then ra = ri - eo."""
    ri, di = erfa.atciq(
        stars.ra_rad, stars.dec_rad, stars.pmra_radyr, stars.pmdec_radyr, stars.plx_arcsec, stars.rv_kms, astrom
    )
    return radec_to_unit(np.asarray(ri) - eo_rad, np.asarray(di))


#: Spacing [s] of the times at which :func:`apparent_directions` computes a star's apparent place exactly; linear
#: interpolation in between errs by at most 2.4e-5" at this spacing (module docstring).
APPARENT_NODE_SPACING_S = 3600.0
_DAY_S = 86400.0
#: Origin of the node grid, a UTC Julian date (2000-01-01 12:00 UTC; any fixed date would do: fixed, so that a row's
#: place does not depend on the other rows of the call).
_NODE_ORIGIN_JD_UTC = 2451545.0


def apparent_directions(
    cat: Catalogue, rows: np.ndarray, jd_utc1: float | np.ndarray, jd_utc2: float | np.ndarray, dut1_s: float = 0.0
) -> np.ndarray:
    """Geocentric apparent unit vectors (N, 3), true equator and equinox of date, of catalogue ``rows`` at UTC
    (jd_utc1 + jd_utc2), a scalar or one time per row. One time: ERFA for each distinct star at that time. One time
    per row: exact at nodes :data:`APPARENT_NODE_SPACING_S` apart on a grid fixed in time (so a row's place does not
    depend on which other rows come with it: a session read in chunks gets the same places) and interpolated between
    them, within 2.4e-5" of ERFA's place (module docstring). ``dut1_s`` is accepted for symmetry with the site
    functions and not used: a geocentric apparent place does not depend on UT1."""
    del dut1_s
    rows = np.atleast_1d(np.asarray(rows, dtype=np.int64))
    jd1, jd2 = np.broadcast_arrays(
        np.atleast_1d(np.asarray(jd_utc1, dtype=np.float64)), np.atleast_1d(np.asarray(jd_utc2, dtype=np.float64))
    )
    if jd1.size not in (1, rows.size):
        raise ValueError(f"expected one time or one per row ({rows.size}), got {jd1.size}")
    if rows.size == 0:
        return np.zeros((0, 3))
    if jd1.size == 1:
        distinct, star_of_row = np.unique(rows, return_inverse=True)
        astrom, eo = frame_astrometry(jd1, jd2)
        return apparent_from_astrometry(stars_at_j2000(cat, distinct), astrom, eo)[star_of_row]
    return _interpolated_directions(cat, rows, (jd1 - _NODE_ORIGIN_JD_UTC) + jd2)


def _interpolated_directions(cat: Catalogue, rows: np.ndarray, days: np.ndarray) -> np.ndarray:
    """Apparent directions of ``rows`` at UTC Julian date :data:`_NODE_ORIGIN_JD_UTC` + ``days`` (module docstring,
    "per epoch"): ERFA for each (star, node) pair a row needs, nodes at whole multiples of the spacing from that
    date, linear in time between a row's two nodes, renormalised."""
    step = APPARENT_NODE_SPACING_S / _DAY_S
    position = days / step
    node = np.floor(position).astype(np.int64)
    weight = position - node
    first = int(node.min())
    span = int(node.max()) - first + 2  # node indices first .. first + span - 1 cover every row's two nodes
    # the (star, node) pairs of each row's lower node; its upper pairs are the same keys + 1
    lower_keys, pair_of_row = np.unique(rows * span + (node - first), return_inverse=True)
    keys = np.union1d(lower_keys, lower_keys + 1)
    lower = np.searchsorted(keys, lower_keys)[pair_of_row]
    upper = np.searchsorted(keys, lower_keys + 1)[pair_of_row]
    star_rows, key_node = np.divmod(keys, span)
    distinct, star_of_key = np.unique(star_rows, return_inverse=True)
    nodes_used, node_of_key = np.unique(key_node, return_inverse=True)
    node_days = (first + nodes_used) * step
    astrom, eo = frame_astrometry(np.full(nodes_used.size, _NODE_ORIGIN_JD_UTC), node_days)
    exact = apparent_from_astrometry(
        stars_at_j2000(cat, distinct).take(star_of_key), astrom[node_of_key], eo[node_of_key]
    )
    r = (1.0 - weight)[:, None] * exact[lower] + weight[:, None] * exact[upper]
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def apparent_radec_deg(
    cat: Catalogue, rows: np.ndarray, jd_utc1: float | np.ndarray, jd_utc2: float | np.ndarray, dut1_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`apparent_directions`, as (ra in [0, 360), dec) [deg]: the session file's ra_deg/dec_deg."""
    return radec_deg_of_units(apparent_directions(cat, rows, jd_utc1, jd_utc2, dut1_s))


def radec_deg_of_units(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ra in [0, 360), dec) [deg] of unit vectors ``r`` (N, 3), as the session file's ra_deg/dec_deg are written:
    ERFA's c2s, one element at a time, so that a direction's angles do not depend on where it sits in the array
    (numpy 1.26's vectorised arctan2 rounds the same input differently in its vector and remainder loops, by an ulp
    that the file's 10 decimals show now and then: a session simulated in chunks must equal the one written whole)."""
    theta, phi = erfa.c2s(np.ascontiguousarray(r, dtype=np.float64))
    return np.degrees(np.mod(theta, 2.0 * np.pi)), np.degrees(phi)


def hip_find(cat: Catalogue, hip_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(catalogue row (int64; meaningless where not found), found (bool)) of each Hipparcos number."""
    hip_ids = np.atleast_1d(np.asarray(hip_ids, dtype=np.int64))
    pos = np.searchsorted(cat.hip, hip_ids)
    pos_c = np.minimum(pos, max(len(cat) - 1, 0))
    found = (pos < len(cat)) & (cat.hip[pos_c] == hip_ids) if len(cat) else np.zeros(hip_ids.shape, dtype=bool)
    return pos_c.astype(np.int64), found


def hip_lookup(cat: Catalogue, hip_ids: np.ndarray) -> np.ndarray:
    """Catalogue row of each Hipparcos number (int64 array). Raises :class:`UserError` naming the first unknown."""
    hip_ids = np.atleast_1d(np.asarray(hip_ids, dtype=np.int64))
    pos_c, found = hip_find(cat, hip_ids)
    if not np.all(found):
        bad = int(hip_ids[np.argmax(~found)])
        raise UserError(f"star_id {bad}: not in the Hipparcos catalogue (within its magnitude limit)")
    return pos_c.astype(np.int64)
