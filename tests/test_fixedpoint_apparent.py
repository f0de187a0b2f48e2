"""The apparent place's per-star work in integers (``onboard.apparent.apparent_place_vectors_q30``: space motion,
light deflection, second-order aberration, the rotation to the equator of date) against float64 of the same float
code at the values the integers represent, with the bound of docs/port-kit.md "Fixed-point formats"; no int64
overflow at the formats' extremes; the range checks. The float code itself is held against ERFA atci13 in
tests/test_apparent_place.py."""

import numpy as np
import pytest

from onboard import apparent as ap
from onboard import timescale as ts
from onboard.earth import ARCSEC_TO_RAD
from onboard.fixedpoint import FixedRangeError

STEP = 2.0**-30  # one Q30 step
#: 0.5 (the result's rounding) + 0.87 (the Q30 matrix: 0.5 |p|_1 <= 0.5 sqrt 3) + 1.73 (the unit vector's two
#: roundings, 0.5 each before and after the reciprocal square root, through a row of M: sqrt 3 x 1) + 0.2 (the
#: changes' roundings in Q48 / Q44, the rsqrt's 1.5e-11, the |beta|^3 terms): 3.3, so 3.5 steps = 3.3e-9 rad
BOUND_STEPS = 3.5
OBSERVER_M_S = np.array([5000.0, -3000.0, 2000.0])  # an orbit's velocity, on top of the Earth's


def _stars(rng, n):
    ra, dec = rng.uniform(0, 2 * np.pi, n), np.arcsin(rng.uniform(-1, 1, n))
    pm_ra, pm_dec, plx = rng.normal(0, 300, n), rng.normal(0, 300, n), rng.uniform(0, 400, n)
    pm_ra[:3], pm_dec[:3], plx[:3] = [8000, -8000, 5000], [-8000, 8000, 0], [770, 768, 0]  # near the formats' limits
    return ap.catalogue_vectors(ra, dec, pm_ra, pm_dec, np.float64), plx


@pytest.mark.parametrize("year", [2001, 2013, 2026, 2049])
def test_apparent_place_in_integers_is_within_its_bound_of_float64(year):
    rng = np.random.default_rng(year)
    (r0, pm), plx = _stars(rng, 2000)
    t = ts.from_calendar(year, 1 + year % 12, 3, 5, 7, 11_000_000)
    r_q, pm_q, plx_q = ap.fixed_catalogue(r0, pm, plx)
    inst = ap.fixed_instant(t, ap.EPOCH_HIPPARCOS_JYEAR, OBSERVER_M_S)
    got = ap.apparent_place_vectors_q30(r_q, pm_q, plx_q, inst)
    plx_mas = plx_q * 2.0**-ap.PARALLAX_FRAC_BITS / (1e-3 * ARCSEC_TO_RAD)
    want = ap.apparent_place_vectors(
        r_q * STEP, pm_q * 2.0**-ap.PM_FRAC_BITS, plx_mas, ap.EPOCH_HIPPARCOS_JYEAR, t, OBSERVER_M_S
    )
    # the formats' range: stars at least 14.4 deg from the Sun (1 + p.e >= 2^-5; the float code clamps at 1e-6)
    away = 1.0 + (r_q * STEP) @ (inst.sun_to_earth_q30 * STEP) > 2.0**-5 + 1e-3
    err_steps = np.abs(got * STEP - want)[away].max() / STEP
    assert err_steps <= BOUND_STEPS, err_steps  # measured 2.5 steps at most over 12 instants


def test_no_overflow_at_the_extremes_of_the_formats():
    rng = np.random.default_rng(5)
    (r0, _), _ = _stars(rng, 300)
    sun_to_earth = np.array([0.6, -0.48, 0.64])
    r0 = np.concatenate([r0, -sun_to_earth[None, :], np.eye(3), -np.eye(3)])  # a star behind the Sun: the clamp
    pm_dir = np.cross(r0, [0.3, 0.5, 0.81])
    pm_dir /= np.linalg.norm(pm_dir, axis=1, keepdims=True)
    pm = pm_dir * ap.MAX_PM_RAD_YR * (1 - 1e-9)
    plx_mas = np.full(len(r0), ap.MAX_PARALLAX_RAD / (1e-3 * ARCSEC_TO_RAD) * (1 - 1e-9))
    r_q, pm_q, plx_q = ap.fixed_catalogue(r0, pm, plx_mas)
    beta = np.array([1.0, -1.0, 1.0]) / np.sqrt(3) * ap.MAX_BETA
    c, s = np.cos(0.7), np.sin(0.7)
    extreme = {
        "years_q20": 1 << (ap.YEARS_FRAC_BITS + 7),
        "earth_bary_q30": np.rint(np.ldexp(sun_to_earth * 1.02, 30)).astype(np.int64),
        "sun_to_earth_q30": np.rint(np.ldexp(sun_to_earth, 30)).astype(np.int64),
        "deflection_k_q70": round(np.ldexp(ap.SUN_DEFLECTION_RAD / 0.983, ap.DEFLECTION_K_FRAC_BITS)),
        "beta_q44": np.rint(np.ldexp(beta, ap.ABERRATION_BETA_FRAC_BITS)).astype(np.int64),
        "tod_q30": np.rint(np.ldexp(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), 30)).astype(np.int64),
    }
    got = ap.apparent_place_vectors_q30(r_q, pm_q, plx_q, ap.FixedInstant(**extreme))
    exact_inst = ap.FixedInstant(
        **{k: v.astype(object) if isinstance(v, np.ndarray) else v for k, v in extreme.items()}
    )
    exact = ap.apparent_place_vectors_q30(r_q.astype(object), pm_q.astype(object), plx_q.astype(object), exact_inst)
    assert np.array_equal(exact.astype(np.int64), got)  # int64 never wrapped
    assert np.abs(exact).max() <= 2**30 + 2  # unit vectors rotated by a Q30 matrix (two roundings)


def test_catalogue_rows_and_instants_outside_the_formats_are_refused():
    r0 = np.array([[1.0, 0.0, 0.0]])
    with pytest.raises(FixedRangeError, match="proper motion"):
        ap.fixed_catalogue(r0, np.array([[0.0, 2.0 * ap.MAX_PM_RAD_YR, 0.0]]), [0.0])
    with pytest.raises(FixedRangeError, match="parallax"):
        ap.fixed_catalogue(r0, np.zeros((1, 3)), [2000.0])  # 9.7e-6 rad > 2^-17
    with pytest.raises(FixedRangeError, match="2\\^-13 c"):
        ap.fixed_instant(ts.from_calendar(2026, 1, 1, 0, 0, 0), ap.EPOCH_J2000_JYEAR, np.array([0.0, 1e5, 0.0]))
    with pytest.raises(FixedRangeError, match="128 years"):
        ap.fixed_instant(ts.from_calendar(2026, 1, 1, 0, 0, 0), 1850.0)
