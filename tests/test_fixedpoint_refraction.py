"""The ground sensor's per-star corrections in integers (``onboard.refraction.topocentric_observed_q30``: diurnal
aberration, then refraction by addition, seed 001 sec. 4) against float64 of the same float code at the same inputs,
with the error bounds of docs/port-kit.md "Fixed-point formats"; no int64 overflow at the formats' extremes (the int64
code equals the same code on exact Python integers); the range checks. The float code itself is held against ERFA
in tests/test_refraction_models.py."""

import math

import numpy as np
import pytest

from onboard import fixedpoint as fx
from onboard import refraction as rf
from onboard.site import Weather

STEP = 2.0**-30  # one Q30 step [rad]
#: 0.5 (the one rounding to Q30) + 1.5 |beta|^2 2^30 (first-order aberration, |beta| <= 2^-18: 0.023 steps)
ABERRATION_BOUND_STEPS = 0.53
#: Sum of the per-component roundings: the result 0.5, the aberrated vector 0.53, cos R 0.8 (R^2 rounded), sin R /
#: sin z times t at most 2^-3.3 x (|t| 1.5 + sin z 1 steps), and R itself (below): 3 steps = 2.8e-9 rad (0.6 mas)
REFRACTION_BOUND_STEPS = 3.0
#: tan z from cos z and sin z rounded half a step each: (1 + tan z) 2^-31 / cos z <= 420 2^-31 at the 87 deg clamp,
#: times dR/dtan = A + 3 B tan^2 <= 2^-8.3 at the largest A, B the formats take: under 1 Q30 step
ANGLE_BOUND_STEPS = 1.0

WEATHERS = {
    "sea level, 10 C": Weather(temp_c=10.0, pressure_hpa=1013.25, rel_humidity=0.5),
    "cold, high pressure": Weather(temp_c=-40.0, pressure_hpa=1080.0, rel_humidity=0.0),
    "hot, mountain": Weather(temp_c=35.0, pressure_hpa=620.0, rel_humidity=0.9),
}


def _directions(n: int, zenith: np.ndarray, z_max_deg: float, seed: int) -> np.ndarray:
    """n unit vectors at zenith distances uniform in [0, z_max] and random azimuths about ``zenith``."""
    rng = np.random.default_rng(seed)
    z = np.radians(rng.uniform(0.0, z_max_deg, n))
    az = rng.uniform(0.0, 2 * np.pi, n)
    e1 = np.cross(zenith, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(zenith, e1)
    return np.cos(z)[:, None] * zenith + np.sin(z)[:, None] * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2)


ZENITH = np.array([0.3, 0.5, math.sqrt(1 - 0.34)])
VELOCITY_M_S = np.array([210.0, -340.0, 120.0])  # 420 m/s: a site at 25 deg latitude


def _fixed_and_float64(weather: Weather | None, n: int = 4000, z_max_deg: float = 87.0, seed: int = 1):
    r_q = fx.quantise_unit_q30(_directions(n, ZENITH, z_max_deg, seed))
    u_q = fx.quantise_unit_q30(ZENITH)
    beta = rf.beta_q48(VELOCITY_M_S)
    coef = None if weather is None else rf.fixed_refraction(weather)
    got = rf.topocentric_observed_q30(r_q, u_q, beta, coef)
    # float64 of the float code at exactly the values the integers represent
    velocity = np.ldexp(beta.astype(np.float64), -rf.BETA_FRAC_BITS) * rf.SPEED_OF_LIGHT_M_S
    want = rf.topocentric_observed(np.ldexp(r_q * 1.0, -30), np.ldexp(u_q * 1.0, -30), velocity, weather)
    return got, want


@pytest.mark.parametrize("name", sorted(WEATHERS))
def test_refraction_by_addition_in_integers_is_within_its_bound_of_float64_to_87_deg(name):
    got, want = _fixed_and_float64(WEATHERS[name])
    err_steps = np.abs(got * STEP - want).max() / STEP
    assert err_steps <= REFRACTION_BOUND_STEPS, err_steps  # measured 2.0 steps at sea level


def test_diurnal_aberration_in_integers_is_one_rounding_from_float64():
    got, want = _fixed_and_float64(None)
    err_steps = np.abs(got * STEP - want).max() / STEP
    assert err_steps <= ABERRATION_BOUND_STEPS, err_steps  # measured 0.501


def test_the_refraction_angle_in_integers_is_within_one_step_of_float64():
    z = np.radians(np.linspace(0.0, 89.0, 891))  # past the 87 deg clamp, where R is frozen
    c_q = np.rint(np.cos(z) * 2**30).astype(np.int64)
    s_q = np.rint(np.sin(z) * 2**30).astype(np.int64)
    for weather in WEATHERS.values():
        coef = rf.fixed_refraction(weather)
        got = rf.refraction_from_true_zenith_q36(c_q, s_q, coef) * 2.0**-rf.R_FRAC_BITS
        want = rf.refraction_from_true_zenith(
            c_q * STEP, s_q * STEP, coef.a_q56 * 2.0**-rf.COEF_FRAC_BITS, coef.b_q56 * 2.0**-rf.COEF_FRAC_BITS
        )
        assert np.abs(got - want).max() <= ANGLE_BOUND_STEPS * STEP  # measured 0.06 steps
        assert np.all(np.diff(got[z < np.radians(86.0)]) > 0)  # R grows with the zenith distance


@pytest.mark.parametrize("sign_b", [1, -1])
def test_no_overflow_at_the_extremes_of_the_formats(sign_b):
    coef = rf.FixedRefraction(1 << (rf.COEF_FRAC_BITS + rf.MAX_A_LOG2), sign_b << (rf.COEF_FRAC_BITS + rf.MAX_B_LOG2))
    zenith = np.array([0.0, 0.0, 1.0])
    r = np.concatenate([_directions(500, zenith, 89.9, 3), np.eye(3), -np.eye(3), [[1, 1, 1] / np.sqrt(3)]])
    r_q = fx.quantise_unit_q30(r)
    u_q = fx.quantise_unit_q30(zenith)
    beta = np.full(3, (1 << (rf.BETA_FRAC_BITS + rf.MAX_BETA_LOG2)) // 2, dtype=np.int64)  # |beta| = 0.87 2^-18
    got = rf.topocentric_observed_q30(r_q, u_q, beta, coef)
    exact = rf.topocentric_observed_q30(r_q.astype(object), u_q.astype(object), beta.astype(object), coef)
    assert np.array_equal(exact.astype(np.int64), got)  # int64 never wrapped
    assert np.abs(exact).max() <= 2**30 + 2  # unit vectors (a rotation by < 2^-3.9 rad and two roundings)
    # and still within the bounds, against float64 of the same steps (topocentric_observed takes a weather, not A, B)
    a, b = coef.a_q56 * 2.0**-rf.COEF_FRAC_BITS, coef.b_q56 * 2.0**-rf.COEF_FRAC_BITS
    r64, u64 = r_q * STEP, u_q * STEP
    topo = r64 + rf.aberration_change(r64, np.ldexp(beta * 1.0, -rf.BETA_FRAC_BITS))
    cz, sz, t = rf.zenith_geometry(topo, u64)
    refr = rf.refraction_from_true_zenith(cz, sz, a, b)
    want = rf.rotate_in_vertical(topo, sz, t, refr, a / np.maximum(cz, rf.MIN_COS_ZENITH))
    inside = cz >= np.cos(np.radians(87.0))  # the model's range (past it both freeze R, and Newton converges slowly)
    assert np.abs(got * STEP - want)[inside].max() <= REFRACTION_BOUND_STEPS * STEP  # measured 1.95 steps
    z = np.radians(np.linspace(0.0, 87.0, 871))
    c_q, s_q = np.rint(np.cos(z) * 2**30).astype(np.int64), np.rint(np.sin(z) * 2**30).astype(np.int64)
    got_r = rf.refraction_from_true_zenith_q36(c_q, s_q, coef) * 2.0**-rf.R_FRAC_BITS
    want_r = rf.refraction_from_true_zenith(c_q * STEP, s_q * STEP, a, b)
    assert np.abs(got_r - want_r).max() <= ANGLE_BOUND_STEPS * STEP  # measured 0.33 steps


def test_coefficients_and_velocities_outside_the_formats_are_refused():
    with pytest.raises(fx.FixedRangeError, match="refraction coefficients"):
        rf.fixed_refraction(Weather(temp_c=0.0, pressure_hpa=5000.0))
    with pytest.raises(fx.FixedRangeError, match="1143 m/s"):
        rf.beta_q48(np.array([2000.0, 0.0, 0.0]))
    assert rf.fixed_refraction(Weather(temp_c=0.0, pressure_hpa=0.0)) == rf.FixedRefraction(0, 0)


def test_integer_square_root_is_the_floor_of_the_root():
    rng = np.random.default_rng(7)
    n = np.concatenate(
        [
            np.arange(0, 300),
            rng.integers(0, 2**62, 2000),
            [(1 << k) + d for k in range(1, 62) for d in (-1, 0, 1)],
            [2**62 - 1],
        ]
    ).astype(np.int64)
    got = fx.isqrt(n)
    assert all(int(g) == math.isqrt(int(v)) for g, v in zip(got, n, strict=True))
