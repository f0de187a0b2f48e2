"""Geocentric apparent place (hostlink.sky.apparent) against an independent pyerfa route.

The project computes pmsafe(J1991.25 -> J2000) + apci13/atciq (CIO based) + ra = ri - eo. The reference here
propagates the catalogue straight to the date (pmsafe), then applies parallax (pmpx), solar light deflection
(ldsun), annual aberration (ab) with the Earth's barycentric velocity (epv00), and rotates with the classical
bias-precession-nutation matrix of date (pnm06a): equinox based, sharing no step with the CIO route.
"""

from __future__ import annotations

import warnings

import erfa
import numpy as np
import pytest

from hostlink.files.times import parse_iso_utc_many, utc_to_tt
from hostlink.sky.apparent import apparent_directions, apparent_radec_deg, hip_lookup
from hostlink.sky.catalogue import HIPPARCOS_EPOCH_JD_TT, load_catalogue
from onboard.camera import radec_to_unit

ARCSEC = np.pi / 648000.0
#: The acceptance bar of the simulator's reference directions (issue 2): 0.01 arcsec.
TOL_RAD = 0.01 * ARCSEC
MAS_TO_RAD = ARCSEC / 1000.0
#: The bound of the apparent place interpolated between hourly nodes (hostlink.sky.apparent's docstring: 2.4e-5").
INTERPOLATION_BOUND_RAD = 2.4e-5 * ARCSEC


def propagated(cat, rows, tt1, tt2):
    """erfa.pmsafe of catalogue ``rows`` from the Hipparcos epoch to TT ``tt1 + tt2``: (ra, dec, pmr, pmd, px, rv)."""
    dec = cat.dec_rad[rows]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)  # non-positive parallaxes: pmsafe's safe override
        return erfa.pmsafe(
            cat.ra_rad[rows],
            dec,
            cat.pmra_masyr[rows] / np.cos(dec) * MAS_TO_RAD,
            cat.pmdec_masyr[rows] * MAS_TO_RAD,
            np.maximum(cat.plx_mas[rows], 0) / 1000.0,
            0.0,
            HIPPARCOS_EPOCH_JD_TT,
            0.0,
            tt1,
            tt2,
        )


def reference_chain(cat, rows, jd_utc1: float, jd_utc2: float) -> np.ndarray:
    tt1, tt2 = utc_to_tt(np.atleast_1d(jd_utc1), np.atleast_1d(jd_utc2))
    ra, de, _, _, px, _ = propagated(cat, rows, tt1[0], tt2[0])
    pvh, pvb = erfa.epv00(tt1[0], tt2[0])
    p = erfa.pmpx(ra, de, 0.0, 0.0, px, 0.0, 0.0, pvb["p"])  # parallax only: motion already applied
    em = np.linalg.norm(pvh["p"])
    p = erfa.ldsun(p, pvh["p"] / em, em)
    v = pvb["v"] / erfa.DC  # au/day -> units of c
    p = erfa.ab(p, v, em, np.sqrt(1.0 - v @ v))
    return p @ erfa.pnm06a(tt1[0], tt2[0]).T


def angle_rad(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


@pytest.mark.parametrize("iso", ["2026-03-14T02:10:00.000Z", "2016-12-31T23:59:59.500Z", "2027-07-01T12:00:00Z"])
def test_apparent_place_matches_independent_erfa_route_to_10_mas(iso):
    cat = load_catalogue(7.0)
    rng = np.random.default_rng(7)
    rows = rng.choice(len(cat), 400, replace=False)
    jd1, jd2 = parse_iso_utc_many([iso])
    ours = apparent_directions(cat, rows, jd1[0], jd2[0])
    ref = reference_chain(cat, rows, jd1[0], jd2[0])
    assert angle_rad(ours, ref).max() < TOL_RAD


def test_fast_movers_and_nearby_stars_match_to_10_mas():
    # Barnard's star (10.4"/yr), Proxima Cen (3.9"/yr, 768 mas parallax), Sirius, 61 Cyg A: the hardest cases
    cat = load_catalogue()
    rows = hip_lookup(cat, [87937, 70890, 32349, 104214])
    for iso in ("2026-03-14T02:10:00.000Z", "1995-06-01T00:00:00.000Z"):
        jd1, jd2 = parse_iso_utc_many([iso])
        ours = apparent_directions(cat, rows, jd1[0], jd2[0])
        assert angle_rad(ours, reference_chain(cat, rows, jd1[0], jd2[0])).max() < TOL_RAD


def test_one_time_per_row_equals_separate_calls():
    cat = load_catalogue(6.0)
    rows = np.array([10, 20, 30])
    jd1, jd2 = parse_iso_utc_many(["2026-03-14T02:10:00Z", "2026-06-14T02:10:00Z", "2026-09-14T02:10:00Z"])
    together = apparent_directions(cat, rows, jd1, jd2)
    for k in range(3):
        alone = apparent_directions(cat, rows[k : k + 1], jd1[k], jd2[k])
        # one time per row is interpolated between hourly nodes (issue 29), one time is ERFA at that time: they agree
        # within the interpolation's bound, 2.4e-5" (hostlink.sky.apparent's docstring)
        assert angle_rad(together[k : k + 1], alone)[0] < INTERPOLATION_BOUND_RAD


def test_radec_degrees_are_the_unit_vectors_in_session_convention():
    cat = load_catalogue(6.0)
    rows = np.arange(50)
    jd1, jd2 = parse_iso_utc_many(["2026-03-14T02:10:00Z"])
    ra, dec = apparent_radec_deg(cat, rows, jd1[0], jd2[0])
    assert np.all((ra >= 0) & (ra < 360))
    r = radec_to_unit(np.radians(ra), np.radians(dec))
    assert angle_rad(r, apparent_directions(cat, rows, jd1[0], jd2[0])).max() < 1e-14  # rounding of a conversion


def test_apparent_place_differs_from_catalogue_by_precession_since_1991():
    cat = load_catalogue(4.0)
    rows = np.arange(len(cat))
    jd1, jd2 = parse_iso_utc_many(["2026-03-14T02:10:00Z"])
    app = apparent_directions(cat, rows, jd1[0], jd2[0])
    icrs = radec_to_unit(cat.ra_rad, cat.dec_rad)
    sep_deg = np.degrees(angle_rad(app, icrs))
    # precession of the equator over 34.9 yr: 50.3"/yr x 34.9 yr = 0.49 deg along the ecliptic; with aberration
    # (<= 20.5") and proper motion every star moves between ~0.2 and ~0.5 deg
    assert 0.15 < np.median(sep_deg) < 0.55


def test_session_without_radec_gets_the_same_reference_directions_as_the_simulator_wrote():
    from dataclasses import replace

    from hostlink.sky.references import session_references
    from hostlink.sky.simulate import seed004_config, simulate

    s = simulate(replace(seed004_config(frames=5, seed=1), false_star_fraction=0.2)).session
    with_radec = session_references(s).r
    without = session_references(replace(s, ra_deg=None, dec_deg=None)).r
    ident = s.star_id != 0
    assert np.all(np.isnan(without[~ident])) and np.all(np.isnan(with_radec[~ident]))
    # the simulator writes ERFA's place at each frame's time; without the columns the place is interpolated between
    # hourly nodes (issue 29): the same within the interpolation's bound
    assert angle_rad(with_radec[ident], without[ident]).max() < INTERPOLATION_BOUND_RAD


def test_apparent_place_per_epoch_matches_erfa_atci13_star_by_star():
    """Issue 29 item 2: one time per row (a streamed session without ra/dec) is computed per epoch (ERFA at nodes an
    hour apart, linear in between), and every star must stay within 0.001" of ERFA's own per-star ``atci13`` (the
    issue's bar); the module's bound for the interpolation is 2.4e-5", checked here too. Three days of rows at random
    times (node ends, mid-node, repeated stars, unsorted) over stars of every declination and proper motion."""
    cat = load_catalogue(6.0)
    rng = np.random.default_rng(29)
    n = 3000
    rows = rng.integers(0, len(cat), n)
    rows[: n // 3] = rows[n // 3 : 2 * (n // 3)]  # the same stars again at other times
    jd1 = np.full(n, 2461113.5)  # 2026-03-14 0h UTC
    jd2 = rng.uniform(0.0, 3.0, n)
    jd2[:10] = np.arange(10) / 24.0  # exactly on nodes
    got = apparent_directions(cat, rows, jd1, jd2)

    tt1, tt2 = utc_to_tt(jd1, jd2)
    j2000 = propagated(cat, rows, 2451545.0, 0.0)  # atci13 takes J2000 star data (its note 1)
    ri, di, eo = erfa.atci13(*j2000, tt1, tt2)  # one full ERFA evaluation per row
    err_arcsec = angle_rad(got, radec_to_unit(ri - eo, di)) / ARCSEC
    assert err_arcsec.max() < 0.001
    assert err_arcsec.max() * ARCSEC < INTERPOLATION_BOUND_RAD
    # a row's place does not depend on the rows that come with it (a session read in chunks gets the same places)
    part = slice(1234, 1300)
    assert np.array_equal(apparent_directions(cat, rows[part], jd1[part], jd2[part]), got[part])


def test_the_session_columns_angles_do_not_depend_on_where_a_direction_sits_in_the_array():
    """radec_deg_of_units gives each direction the same ra/dec whatever the rows around it (a session simulated in
    chunks equals the one written whole, byte for byte): shifted and misaligned copies agree bit for bit (numpy 1.26's
    vectorised arctan2 did not), and the angles are onboard's unit_to_radec to rounding (1e-12 deg, ~1e4 ulp of 360)."""
    from hostlink.sky.apparent import radec_deg_of_units
    from onboard.camera import unit_to_radec

    rng = np.random.default_rng(7)
    r = rng.normal(size=(4099, 3))
    r /= np.linalg.norm(r, axis=1)[:, None]
    ra, dec = radec_deg_of_units(r)
    for offset in range(1, 9):
        buffer = np.empty(r[offset:].size + 1)
        misaligned = buffer[1:].reshape(-1, 3)
        misaligned[:] = r[offset:]
        ra_k, dec_k = radec_deg_of_units(misaligned)
        np.testing.assert_array_equal(ra_k, ra[offset:])
        np.testing.assert_array_equal(dec_k, dec[offset:])
    ra_ref, dec_ref = unit_to_radec(r)
    np.testing.assert_allclose(ra, np.degrees(ra_ref), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dec, np.degrees(dec_ref), rtol=0, atol=1e-12)
    assert np.all((ra >= 0) & (ra < 360))
