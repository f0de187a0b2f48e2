"""Onboard fixed-point time, Earth orientation and apparent place against pyerfa (IAU 2006/2000A), 2000-2050."""

from __future__ import annotations

import erfa
import numpy as np
import pytest

from onboard import apparent as ap
from onboard import earth
from onboard import timescale as ts
from onboard.site import Site

ARCSEC = np.pi / 648000.0
RNG_SEED = 20240611
#: Epochs spread over the acceptance span 2000-2050 (TT days after J2000.0).
N_EPOCHS = 40


def _epochs(n: int = N_EPOCHS, seed: int = RNG_SEED) -> list[ts.FixedTime]:
    rng = np.random.default_rng(seed)
    return [ts.from_julian_date(2451545.0, d) for d in rng.uniform(0.0, 50 * 365.25, n)]


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * np.asarray(angle, dtype=np.float64)))


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


# ------------------------------------------------------------------------------------------------ fixed-point time


@pytest.mark.parametrize(
    "fields",
    [
        (2000, 1, 1, 12, 0, 0),
        (2000, 1, 1, 0, 0, 0),
        (1999, 12, 31, 23, 59, 59_999_000),
        (2014, 7, 9, 11, 48, 59_600_000),
        (2024, 2, 29, 6, 30, 15_250_000),
        (2050, 12, 31, 18, 0, 1_000),
    ],
)
@pytest.mark.filterwarnings("ignore::erfa.ErfaWarning")  # ERFA calls years past its leap-second table "dubious"
def test_calendar_time_matches_erfa_dtf2d(fields):
    y, mo, d, h, mi, us = fields
    t = ts.from_calendar(y, mo, d, h, mi, us)
    jd1, jd2 = ts.to_julian_date(t)
    e1, e2 = erfa.dtf2d("UTC", y, mo, d, h, mi, us / 1e6)
    # 2^-32 day rounding is 10 us at most; allow 20 us (float64 Julian dates carry ~1 us here)
    assert abs(((jd1 - e1) + (jd2 - e2)) * 86400.0) < 20e-6


def test_adding_seconds_carries_across_days_exactly():
    t = ts.from_calendar(2021, 6, 30, 11, 59, 59_000_000)  # one second before noon = the day boundary of the count
    later = ts.add_seconds(t, 1.5)
    assert int(later.day) == int(t.day) + 1
    # the carried fraction is 0.5 s to the 2^-32 day unit (10 us)
    assert abs(float(later.frac) / 2**32 * 86400.0 - 0.5) < 1e-5
    back = ts.add_seconds(later, -1.5)
    assert int(back.day) == int(t.day) and abs(int(back.frac) - int(t.frac)) <= 1  # one unit of rounding


def test_tt_from_utc_matches_erfa_with_the_leap_second_count():
    t = ts.from_calendar(2019, 3, 1, 3, 4, 5_000_000)
    jd1, jd2 = ts.to_julian_date(ts.tt_from_utc(t, tai_minus_utc_s=37))
    u1, u2 = erfa.dtf2d("UTC", 2019, 3, 1, 3, 4, 5.0)
    e1, e2 = erfa.taitt(*erfa.utctai(u1, u2))
    assert abs(((jd1 - e1) + (jd2 - e2)) * 86400.0) < 20e-6  # 2^-32-day rounding of two offsets


# ------------------------------------------------------------------------------------------------ Earth orientation


def test_earth_rotation_angle_in_fixed_point_matches_erfa_era00():
    worst = 0.0
    for t in _epochs():
        jd1, jd2 = ts.to_julian_date(t)
        worst = max(worst, abs(_wrap(earth.bam_to_rad(earth.earth_rotation_angle_bam(t)) - erfa.era00(jd1, jd2))))
    # 2^-32-turn truncation of the rate times the day fraction (0.0003") plus float64 conversion
    assert worst < 0.001 * ARCSEC


def test_binary_angle_sine_and_cosine_keep_float32_precision_at_any_angle():
    rng = np.random.default_rng(RNG_SEED)
    bam = rng.integers(0, 2**63, 2000, dtype=np.uint64) * np.uint64(2) + np.uint64(1)
    s32, c32 = earth.bam_sincos(bam, np.float32)
    angle = earth.bam_to_rad(bam)
    err = np.hypot(s32 - np.sin(angle), c32 - np.cos(angle))
    raw = angle.astype(np.float32)
    raw_err = np.hypot(np.sin(raw) - np.sin(angle), np.cos(raw) - np.cos(angle))
    # reduced argument |x| <= pi/4 rounds to 3e-8 and sin/cos near 1 to 6e-8 each: 1.5e-7 (0.03") bounds it, while
    # a float32 angle in radians up to 2 pi rounds to 2.4e-7 by itself
    assert err.max() < 1.5e-7
    assert raw_err.max() > 1.5e-7


def test_precession_angles_are_the_iau2006_fukushima_williams_angles():
    for t in _epochs(10):
        jd1, jd2 = ts.to_julian_date(t)
        ref = erfa.pfw06(jd1, jd2)
        got64 = earth.precession_angles(ts.julian_centuries(t, np.float64))
        got32 = earth.precession_angles(ts.julian_centuries(t, np.float32))
        for a64, a32, e in zip(got64, got32, ref, strict=True):
            assert abs(a64 - e) < 1e-6 * ARCSEC  # same polynomials: float64 rounding only
            assert abs(float(a32) - e) < 0.006 * ARCSEC  # float32 of a 0.41 rad angle: ulp 3e-8 rad = 0.006"


def test_truncated_nutation_stays_within_its_budget_against_iau2000a():
    worst_psi = worst_eps = 0.0
    for t in _epochs():
        jd1, jd2 = ts.to_julian_date(t)
        dpsi, deps = earth.nutation(ts.julian_centuries(t, np.float64))
        e_psi, e_eps = erfa.nut06a(jd1, jd2)
        worst_psi, worst_eps = max(worst_psi, abs(dpsi - e_psi)), max(worst_eps, abs(deps - e_eps))
    # 30 of the 77 IAU 2000B terms: measured 0.014" / 0.006" over 20000 epochs of 2000-2050
    assert worst_psi < 0.016 * ARCSEC
    assert worst_eps < 0.008 * ARCSEC


@pytest.mark.parametrize("dtype, bound_arcsec", [(np.float64, 0.012), (np.float32, 0.03)])
def test_true_of_date_matrix_matches_erfa_pnm06a(dtype, bound_arcsec):
    rng = np.random.default_rng(RNG_SEED)
    r = rng.normal(size=(500, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    worst = 0.0
    for t in _epochs():
        jd1, jd2 = ts.to_julian_date(t)
        got = r.astype(dtype) @ earth.true_of_date_matrix(t, dtype).T
        worst = max(worst, _angle_between(got, r @ erfa.pnm06a(jd1, jd2).T).max())
    # float64: nutation truncation (0.011"); float32 adds rounding of the matrix product (measured 0.02")
    assert worst < bound_arcsec * ARCSEC


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_sidereal_time_matches_erfa_gmst06_and_gst06a(dtype):
    worst_mean = worst_app = 0.0
    for t in _epochs():
        jd1, jd2 = ts.to_julian_date(t)
        gmst = earth.bam_to_rad(earth.sidereal_time_bam(t, t, apparent=False, dtype=dtype))
        gast = earth.bam_to_rad(earth.sidereal_time_bam(t, t, dtype=dtype))
        worst_mean = max(worst_mean, abs(_wrap(gmst - erfa.gmst06(jd1, jd2, jd1, jd2))))
        worst_app = max(worst_app, abs(_wrap(gast - erfa.gst06a(jd1, jd2, jd1, jd2))))
    assert worst_mean < 0.002 * ARCSEC  # same polynomial; 2^-32-turn steps and float32 of a 0.01 rad term
    assert worst_app < 0.015 * ARCSEC  # plus the nutation truncation in dpsi cos(eps) (0.011")


@pytest.mark.filterwarnings("ignore::erfa.ErfaWarning")  # ERFA calls years past its leap-second table "dubious"
def test_local_zenith_is_the_geodetic_vertical_rotated_by_erfa_sidereal_time():
    site = Site(31.945218, 120.293107, 10.0)
    for t in _epochs(10):
        jd1, jd2 = ts.to_julian_date(t)
        # t is taken as UTC here: compare against ERFA with the same UT1 and TT
        ut1 = erfa.utcut1(jd1, jd2, 0.2)
        tt = erfa.taitt(*erfa.utctai(jd1, jd2))
        last = erfa.gst06a(ut1[0], ut1[1], tt[0], tt[1]) + np.radians(site.lon_deg)
        phi = np.radians(site.lat_deg)
        want = np.array([np.cos(phi) * np.cos(last), np.cos(phi) * np.sin(last), np.sin(phi)])
        leap = int(round(erfa.dat(*erfa.jd2cal(jd1, jd2))))
        got = earth.zenith_true_of_date(t, site, dut1_s=0.2, tai_minus_utc_s=leap, dtype=np.float32)
        # float32 zenith: GAST (0.011") plus float32 rounding of the vector (0.02")
        assert _angle_between(got, want) < 0.04 * ARCSEC
        frame = earth.local_frame_matrix(t, site, 0.2, leap, np.float64)
        assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-14)  # rows N, U, E orthonormal
        assert np.isclose(np.linalg.det(frame), 1.0)  # right-handed as (N, U, E) in seed 001's order


# ------------------------------------------------------------------------------------------------ Earth's orbit


def test_compact_earth_model_matches_erfa_epv00():
    worst_v = worst_p = 0.0
    for t in _epochs(200):
        jd1, jd2 = ts.to_julian_date(t)
        pvh, pvb = erfa.epv00(jd1, jd2)
        p, v, h = ap.earth_barycentric_state(t, np.float64)
        worst_v = max(worst_v, np.linalg.norm(v - pvb["v"]) * ap.ASTRONOMICAL_UNIT_M / 86400.0)
        worst_p = max(worst_p, np.linalg.norm(p - pvb["p"]), np.linalg.norm(h - pvh["p"]))
    assert worst_v < 5.0  # m/s; 5 m/s is 0.0035" of aberration (measured 3.3 m/s)
    assert worst_p < 0.004  # AU; moves a 0.77" parallax by 0.003" (measured 0.0025 AU)


# ------------------------------------------------------------------------------------------------ apparent place


def _random_stars(rng, n):
    ra = rng.uniform(0, 2 * np.pi, n)
    dec = np.arcsin(rng.uniform(-1, 1, n))
    pm_ra = rng.normal(0, 300, n)  # mas/yr, mu_alpha*
    pm_dec = rng.normal(0, 300, n)
    plx = rng.uniform(0, 400, n)  # mas
    return ra, dec, pm_ra, pm_dec, plx


def _erfa_apparent_tod(ra, dec, pm_ra, pm_dec, plx, t: ts.FixedTime) -> tuple[np.ndarray, np.ndarray]:
    """ERFA atci13 (J2000 star data) -> TOD unit vectors (RA = ri - eo), and the Sun's direction."""
    jd1, jd2 = ts.to_julian_date(t)
    mas = 1e-3 * ARCSEC
    ri, di, eo = erfa.atci13(ra, dec, pm_ra * mas / np.cos(dec), pm_dec * mas, plx * 1e-3, 0.0, jd1, jd2)
    a = ri - eo
    pvh, _ = erfa.epv00(jd1, jd2)
    return np.stack([np.cos(di) * np.cos(a), np.cos(di) * np.sin(a), np.sin(di)], axis=1), -pvh["p"]


@pytest.mark.parametrize("dtype, bound_arcsec", [(np.float64, 0.02), (np.float32, 0.06)])
def test_apparent_place_matches_erfa_atci13_over_2000_to_2050(dtype, bound_arcsec):
    rng = np.random.default_rng(RNG_SEED)
    worst = 0.0
    for t in _epochs(25):
        stars = _random_stars(rng, 300)
        want, sun = _erfa_apparent_tod(*stars, t)
        r0 = np.stack([np.cos(stars[1]) * np.cos(stars[0]), np.cos(stars[1]) * np.sin(stars[0]), np.sin(stars[1])], 1)
        away = _angle_between(r0, np.broadcast_to(sun, r0.shape)) > np.radians(10)  # "stars away from the Sun"
        got = ap.apparent_place(*stars, ap.EPOCH_J2000_JYEAR, t, dtype=dtype)
        assert got.dtype == dtype
        worst = max(worst, _angle_between(got, want)[away].max())
    # acceptance is 0.1"; measured 0.009" (float64: nutation truncation, orbit model) and 0.037" (float32 rounding)
    assert worst < bound_arcsec * ARCSEC


def test_apparent_place_from_a_hipparcos_epoch_catalogue_matches_erfa():
    rng = np.random.default_rng(RNG_SEED + 1)
    ra, dec, pm_ra, pm_dec, plx = _random_stars(rng, 200)
    mas = 1e-3 * ARCSEC
    # ERFA's route: pmsafe from J1991.25 to J2000 (rv = 0), then atci13
    r2, d2, pr2, pd2, px2, _ = erfa.pmsafe(
        ra, dec, pm_ra * mas / np.cos(dec), pm_dec * mas, plx * 1e-3, 0.0, 2448349.0625, 0.0, 2451545.0, 0.0
    )
    t = ts.from_calendar(2031, 5, 17, 21, 0, 0)
    jd1, jd2 = ts.to_julian_date(t)
    ri, di, eo = erfa.atci13(r2, d2, pr2, pd2, px2, 0.0, jd1, jd2)
    want = np.stack([np.cos(di) * np.cos(ri - eo), np.cos(di) * np.sin(ri - eo), np.sin(di)], axis=1)
    got = ap.apparent_place(ra, dec, pm_ra, pm_dec, plx, ap.EPOCH_HIPPARCOS_JYEAR, t, dtype=np.float32)
    # same budget as the J2000 test; 40 years of linear space motion is rigorous to 1e-6" for rv = 0
    assert _angle_between(got, want).max() < 0.06 * ARCSEC


def test_observer_velocity_adds_orbital_aberration_as_erfa_apcs():
    rng = np.random.default_rng(RNG_SEED + 2)
    ra, dec, pm_ra, pm_dec, plx = _random_stars(rng, 200)
    t = ts.from_calendar(2027, 9, 1, 4, 0, 0)
    jd1, jd2 = ts.to_julian_date(t)
    v_obs = np.array([-4100.0, 5300.0, 3200.0])  # m/s, a low-Earth-orbit speed (7.5 km/s, 5" of aberration)
    pv = np.zeros((), dtype=erfa.dt_pv)
    pv["p"], pv["v"] = (6.9e6, 0.0, 0.0), v_obs  # position [m] only moves parallax by 1e-6": irrelevant
    astrom = erfa.apcs13(jd1, jd2, pv)
    mas = 1e-3 * ARCSEC
    # apcs13's astrom has an identity bias-precession-nutation: atciq returns GCRS, rotated to TOD here
    ri, di = erfa.atciq(ra, dec, pm_ra * mas / np.cos(dec), pm_dec * mas, plx * 1e-3, 0.0, astrom)
    gcrs = np.stack([np.cos(di) * np.cos(ri), np.cos(di) * np.sin(ri), np.sin(di)], axis=1)
    want = gcrs @ erfa.pnm06a(jd1, jd2).T
    _, sun = _erfa_apparent_tod(ra, dec, pm_ra, pm_dec, plx, t)
    r0 = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], 1)
    away = _angle_between(r0, np.broadcast_to(sun, r0.shape)) > np.radians(10)
    got = ap.apparent_place(ra, dec, pm_ra, pm_dec, plx, 2000.0, t, observer_velocity_gcrs_m_s=v_obs, dtype=np.float32)
    assert _angle_between(got, want)[away].max() < 0.06 * ARCSEC  # the geocentric budget: the velocity is exact
    geocentric = ap.apparent_place(ra, dec, pm_ra, pm_dec, plx, 2000.0, t, dtype=np.float32)
    assert _angle_between(got, geocentric).max() > 4.0 * ARCSEC  # and the input really acts (7.5 km/s ~ 5")


def test_float32_apparent_place_tracks_the_float64_run_of_the_same_code():
    rng = np.random.default_rng(RNG_SEED + 3)
    worst = 0.0
    for t in _epochs(10):
        stars = _random_stars(rng, 500)
        a32 = ap.apparent_place(*stars, 1991.25, t, dtype=np.float32)
        a64 = ap.apparent_place(*stars, 1991.25, t, dtype=np.float64)
        worst = max(worst, _angle_between(a32, a64).max())
    # float32 unit vectors: storage (0.01"), one addition of all corrections (0.01"), the rotation (0.02")
    assert worst < 0.05 * ARCSEC
