"""The one reference-direction service (hostlink.sky.references) against ERFA's observed place, and its two routes
(the file's ra_deg/dec_deg, Hipparcos through ERFA) against each other."""

from __future__ import annotations

from dataclasses import replace

import erfa
import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.files.session import Session
from hostlink.files.times import parse_iso_utc_many
from hostlink.sky.apparent import apparent_from_astrometry, frame_astrometry, stars_at_j2000
from hostlink.sky.catalogue import load_catalogue
from hostlink.sky.references import session_references, session_with_references
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from hostlink.sky.site import local_north_east, zenith_distance_rad, zenith_true_of_date
from onboard.site import Site, Weather

ARCSEC = np.pi / 648000.0
SITE = Site(39.9, 116.4, 50.0)
WEATHER = Weather(10.0, 1013.25, 0.5)
DUT1_S = 0.3
TIMES = ("2026-03-14T18:10:00.000Z", "2026-03-14T18:40:00.000Z")
MAX_ZD_DEG = 75.0
#: Service vs erfa.atco13 with air: the onboard refraction inverts A tan z + B tan^3 z exactly where ERFA takes one
#: Newton step (3 mas at 75 deg, hostlink/sky/site.py), plus ERFA's small-angle lift (0.1 mas); 5 mas covers both
#: (measured 3.0 mas over 300 stars to 75 deg).
ATCO13_AIR_BOUND_RAD = 0.005 * ARCSEC
#: In vacuo only the aberration differs: by two velocities in turn vs their sum and the site parallax (3e-5" at
#: most; measured 0.008 mas).
ATCO13_VACUUM_BOUND_RAD = 1e-4 * ARCSEC


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


def _hipparcos_session() -> tuple[Session, list[np.ndarray]]:
    """Two frames of Hp <= 6 stars above 75 deg zenith distance at SITE, without ra_deg/dec_deg (the Hipparcos
    route), plus one unidentified row per frame; and each frame's catalogue rows."""
    cat = load_catalogue(6.0)
    stars = stars_at_j2000(cat)
    rows, ids, times = [], [], []
    for iso in TIMES:
        jd1, jd2 = parse_iso_utc_many([iso])
        astrom, eo = frame_astrometry(jd1, jd2)
        r_app = apparent_from_astrometry(stars, astrom[0], eo[0])
        zen = zenith_true_of_date(jd1[0], jd2[0], SITE, DUT1_S)
        sel = np.flatnonzero(zenith_distance_rad(r_app, zen) < np.radians(MAX_ZD_DEG))[:150]
        rows.append(sel)
        ids.append(np.concatenate([cat.hip[sel], [0]]))
        times.append([iso] * (sel.size + 1))
    n = [len(i) for i in ids]
    session = Session(
        frame=np.repeat(np.arange(len(TIMES)), n),
        t_utc=np.array(sum(times, []), dtype=object),
        star_id=np.concatenate(ids).astype(np.int64),
        x_px=np.zeros(sum(n)),
        y_px=np.zeros(sum(n)),
    )
    return session, rows


@pytest.mark.parametrize("weather", [None, WEATHER])
def test_site_references_are_erfa_atco13_observed_place_of_hipparcos_stars(weather):
    session, cat_rows = _hipparcos_session()
    refs = session_references(session, SITE, weather, DUT1_S)
    assert refs.source == "hipparcos" and refs.n_unidentified == len(TIMES)
    assert np.all(np.isnan(refs.r[session.star_id == 0])) and not np.any(refs.usable[session.star_id == 0])
    stars = stars_at_j2000(load_catalogue(6.0))
    air = (0.0, 0.0, 0.0, 0.55) if weather is None else (1013.25, 10.0, 0.5, 0.55)
    bound = ATCO13_VACUUM_BOUND_RAD if weather is None else ATCO13_AIR_BOUND_RAD
    for k, sl in enumerate(session.frame_slices()):
        jd1, jd2 = parse_iso_utc_many([TIMES[k]])
        s = stars.take(cat_rows[k])
        aob, zob, *_ = erfa.atco13(
            s.ra_rad, s.dec_rad, s.pmra_radyr, s.pmdec_radyr, s.plx_arcsec, s.rv_kms, jd1[0], jd2[0], DUT1_S,
            np.radians(SITE.lon_deg), np.radians(SITE.lat_deg), SITE.height_m, 0.0, 0.0, *air,
        )  # fmt: skip
        r = refs.r[sl][refs.usable[sl]]
        zen = zenith_true_of_date(jd1[0], jd2[0], SITE, DUT1_S)
        north, east = local_north_east(zen)
        d_zd = zenith_distance_rad(r, zen) - zob
        d_az = np.angle(np.exp(1j * (np.arctan2(r @ east, r @ north) - aob))) * np.sin(zob)
        assert np.abs(d_zd).max() < bound
        assert np.abs(d_az).max() < bound


@pytest.fixture(scope="module")
def ground_session():
    cfg = SimConfig(
        camera=seed004_camera(),
        frames=6,
        noise_px=0.0,
        min_stars=5,
        maglim=6.0,
        seed=11,
        site=SITE,
        weather=WEATHER,
        zenith_range_deg=(5.0, 75.0),
        false_star_fraction=0.2,
    )
    return simulate(cfg).session


def test_the_file_route_and_the_hipparcos_route_give_the_same_observed_references(ground_session):
    s = ground_session
    from_file = session_references(s, SITE, WEATHER, DUT1_S)
    from_hipparcos = session_references(replace(s, ra_deg=None, dec_deg=None), SITE, WEATHER, DUT1_S)
    assert (from_file.source, from_hipparcos.source) == ("file", "hipparcos")
    np.testing.assert_array_equal(from_file.usable, s.star_id != 0)
    np.testing.assert_array_equal(from_hipparcos.usable, s.star_id != 0)
    ok = from_file.usable
    # the simulator wrote ERFA's apparent place at each frame's time; without the columns it is interpolated between
    # hourly nodes (issue 29): the same within the interpolation's bound, 2.4e-5" (hostlink.sky.apparent)
    assert _angles(from_file.r[ok], from_hipparcos.r[ok]).max() < 2.4e-5 * ARCSEC
    assert "refraction" in from_file.refraction and "10 C, 1013.25 hPa" in from_file.refraction


def test_a_site_moves_the_references_by_the_aberration_then_lifts_them_by_erfa_refraction(ground_session):
    from hostlink.sky.site import refraction_truth_rad

    geocentric = session_references(ground_session)
    vacuum = session_references(ground_session, SITE, None, DUT1_S)
    air = session_references(ground_session, SITE, WEATHER, DUT1_S)
    ok = geocentric.usable
    assert geocentric.refraction == "none" and "diurnal aberration only" in vacuum.refraction
    shift_vacuum = _angles(geocentric.r[ok], vacuum.r[ok]) / ARCSEC
    # diurnal aberration at 39.9 deg: beta cos(lat) = 0.245" at most, and never zero across a field
    assert 0.0 < shift_vacuum.min() and shift_vacuum.max() < 0.246
    jd1, jd2 = ground_session.frame_times_jd()
    frame_of_row = np.repeat(np.arange(jd1.size), np.diff(ground_session.frame_starts))[ok]
    zen = zenith_true_of_date(jd1, jd2, SITE, DUT1_S)[frame_of_row]
    zd_vacuum, zd_air = (np.arccos(np.sum(v.r[ok] * zen, axis=1)) for v in (vacuum, air))
    lift = zd_vacuum - zd_air
    # straight up by ERFA's refraction at that zenith distance (stars reach 79 deg at the edge of a 75-deg field):
    # ERFA's one-step inverse vs the exact one, 20 mas at 80 deg (hostlink/sky/site.py), and the lift is all there is
    np.testing.assert_allclose(lift, refraction_truth_rad(zd_vacuum, WEATHER), rtol=0, atol=0.02 * ARCSEC)
    np.testing.assert_allclose(_angles(vacuum.r[ok], air.r[ok]), lift, rtol=0, atol=1e-4 * ARCSEC)


def test_a_session_rewritten_with_its_references_reads_them_back(ground_session):
    refs = session_references(ground_session, SITE, WEATHER, DUT1_S)
    rewritten = session_with_references(ground_session, refs)
    again = session_references(rewritten)
    np.testing.assert_array_equal(again.usable, refs.usable)
    assert _angles(again.r[refs.usable], refs.r[refs.usable]).max() < 1e-12  # ra/dec in degrees and back
    assert np.all(np.isnan(rewritten.ra_deg[~refs.usable]))
    np.testing.assert_array_equal(rewritten.x_px, ground_session.x_px)  # only the reference columns change


def test_weather_without_a_site_is_refused_in_one_line(ground_session):
    with pytest.raises(UserError, match="weather without a site"):
        session_references(ground_session, None, WEATHER)
