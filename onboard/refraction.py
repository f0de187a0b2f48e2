"""Atmospheric refraction for ground and ship-borne sensors (seed 001), dtype-generic.

Two models of the refraction R (apparent elevation minus true elevation), both functions of the *apparent* (observed)
zenith distance z_a, as their sources define them:

- ``"atan"``: R = A tan z_a + B tan^3 z_a with A, B from temperature, pressure, humidity and wavelength
  (:func:`refraction_coefficients`; Green 1987 eq. 4.31 with the refractivity of Hohenkerk & Sinclair 1985 /
  Rueger 2002 and the scale-height ratio of Stone 1996: the model of ERFA refco). Against ERFA (refco + atioq)
  it agrees to 0.02" up to 80 deg (ERFA takes one Newton step for the true-zenith form, this module two: the
  exact inverse); against ray tracing it is good to about 0.05" up to 75 deg and 0.6" at 80 deg (ERFA's figures).
- ``"seed001"``: R = 60.2" tan z_a (1 + M + N) (seed 001 eq. 13-17), M = -0.00383 T / (1 + 0.00367 T), N = H/760 - 1
  with H the barometer reading in **mmHg** (the paper says Pa; eq. 15 is only right in mmHg: 1 hPa = 0.750062 mmHg),
  reduced by eq. 16 for latitude (gravity) when the latitude is given; the mercury-temperature term of eq. 16 is zero
  for an electronic barometer. It is :func:`refraction_coefficients` with B = 0.

The reference-quantity correction (seed 001 sec. 4, eq. 20-25) adds R to the elevation of the *true* catalogue
direction, so it needs R as a function of the true zenith distance z_t = z_a + R(z_a). Seed 001 simply evaluates
the formula at z_t, an error R'(z) R that stays under 0.1" only to about 60 deg (0.8" at 75 deg).
:func:`refraction_from_true_zenith` solves z_t = z_a + A tan z_a + B tan^3 z_a instead, by Newton's method from
z_a = z_t (the first step is ERFA atioq's formula; each further step squares the error: two steps leave < 1e-4"
at 80 deg), so the lift is the exact inverse of the model at every zenith distance.

A ground sensor sees topocentric directions: before the atmosphere bends them, the site's rotation velocity
(465 m/s cos(lat), ``onboard.earth.site_velocity_tod_m_s``) aberrates them by up to 0.32" (diurnal aberration).
:func:`topocentric_observed` is the one place where the sensor turns geocentric apparent directions (the session's
``ra_deg, dec_deg``) into what it observes from a site: diurnal aberration (the relativistic formula of
``onboard.apparent.aberration_change``, by the site velocity alone), then refraction by addition
(:func:`refract_toward_zenith`). Aberrating by the site velocity after the annual aberration, instead of by the sum
of the two velocities (ERFA apco13), differs by O(beta_earth beta_site) = 1.6e-10 rad (3e-5").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.apparent import SPEED_OF_LIGHT_M_S, aberration_change
from onboard.fixedpoint import FixedRangeError, Q, div_round, isqrt, quantise_unit_q30, rshift_round
from onboard.site import Weather

ARCSEC_TO_RAD = np.pi / 648000.0
#: hPa -> mmHg (760 mmHg = 1013.25 hPa; the torr and the conventional mmHg differ by 1.4e-7).
MMHG_PER_HPA = 760.0 / 1013.25
#: Newton steps for the true-zenith-distance form (bounded cost; 2 are exact to < 1e-4" up to 80 deg).
TRUE_ZENITH_NEWTON_STEPS = 2
#: Below this cosine of zenith distance (about 87 deg) refraction is frozen at its value there: the tan z models
#: are meaningless near the horizon (ERFA atioq uses the same limit, sin(elevation) >= 0.05).
MIN_COS_ZENITH = 0.05


def refraction_coefficients(weather: Weather) -> tuple[float, float]:
    """(A, B) [rad] of R = A tan z_a + B tan^3 z_a for optical wavelengths (Green 1987 eq. 4.31; the refco model).

    Water vapour pressure from the saturation pressure (Gill 1982 eq. A4.5-A4.7) and relative humidity (Crane 1976
    eq. 2.5.5); refractivity n - 1 from pressure, temperature, vapour pressure and wavelength; beta = 4.4474e-6 T_K
    (Stone 1996 eq. 9, adjusted); A = gamma (1 - beta), B = -gamma (beta - gamma / 2). A configuration-time
    computation (Python floats): the sensor stores A and B.
    """
    t = min(max(float(weather.temp_c), -150.0), 200.0)
    p = min(max(float(weather.pressure_hpa), 0.0), 10000.0)
    rh = min(max(float(weather.rel_humidity), 0.0), 1.0)
    wl = min(max(float(weather.wavelength_um), 0.1), 100.0)
    if p > 0.0:
        ps = 10.0 ** ((0.7859 + 0.03477 * t) / (1.0 + 0.00412 * t)) * (1.0 + p * (4.5e-6 + 6e-10 * t * t))
        pw = rh * ps / (1.0 - (1.0 - rh) * ps / p)
    else:
        pw = 0.0
    tk = t + 273.15
    wl2 = wl * wl
    gamma = ((77.53484e-6 + (4.39108e-7 + 3.666e-9 / wl2) / wl2) * p - 11.2684e-6 * pw) / tk
    beta = 4.4474e-6 * tk
    return gamma * (1.0 - beta), -gamma * (beta - gamma / 2.0)


def seed001_coefficient_rad(temp_c: float, pressure_hpa: float, lat_rad: float | None = None) -> float:
    """K [rad] of seed 001's R = K tan z_a: K = 60.2" (1 + M + N) (eq. 13-17), pressure converted hPa -> mmHg,
    with eq. 16's gravity reduction H = H' (1 - 0.00264 cos 2 phi) when ``lat_rad`` is given."""
    m = -0.00383 * temp_c / (1.0 + 0.00367 * temp_c)  # eq. 14
    h_mmhg = pressure_hpa * MMHG_PER_HPA
    if lat_rad is not None:
        h_mmhg *= 1.0 - 0.00264 * np.cos(2.0 * lat_rad)  # eq. 16, barometer at air temperature (T' = T)
    n = h_mmhg / 760.0 - 1.0  # eq. 15
    return 60.2 * ARCSEC_TO_RAD * (1.0 + m + n)  # eq. 13, 17


def model_coefficients(weather: Weather, model: str = "atan", lat_rad: float | None = None) -> tuple[float, float]:
    """(A, B) [rad] of either model in the common form A tan z_a + B tan^3 z_a."""
    if model == "atan":
        return refraction_coefficients(weather)
    if model == "seed001":
        return seed001_coefficient_rad(weather.temp_c, weather.pressure_hpa, lat_rad), 0.0
    raise ValueError(f"unknown refraction model {model!r} (expected 'atan' or 'seed001')")


def refraction_apparent(cos_za, sin_za, a_rad: float, b_rad: float):
    """R(z_a) = A tan z_a + B tan^3 z_a [rad] from cos and sin of the apparent zenith distance (dtype of input)."""
    dt = np.asarray(cos_za).dtype.type
    c = np.maximum(cos_za, dt(MIN_COS_ZENITH))
    tz = sin_za / c
    return (dt(a_rad) + dt(b_rad) * tz * tz) * tz


def refraction_from_true_zenith(cos_zt, sin_zt, a_rad: float, b_rad: float, steps: int = TRUE_ZENITH_NEWTON_STEPS):
    """R [rad] such that z_t = z_a + R(z_a), z_a = z_t - R, from cos and sin of the true zenith distance.

    Newton on g(z_a) = z_a + A tan z_a + B tan^3 z_a - z_t from z_a = z_t: the first step is
    (A tan z_t + B tan^3 z_t) / (1 + (A + 3 B tan^2 z_t) sec^2 z_t) (ERFA atioq); later steps rotate (cos, sin) of
    z_a by the current R rather than calling trig functions of a large angle.
    """
    dt = np.asarray(cos_zt).dtype.type
    a, b = dt(a_rad), dt(b_rad)
    r = np.zeros_like(cos_zt)
    for _ in range(steps):
        cr, sr = np.cos(r), np.sin(r)
        c = np.maximum(cos_zt * cr + sin_zt * sr, dt(MIN_COS_ZENITH))  # cos(z_t - r)
        s = sin_zt * cr - cos_zt * sr  # sin(z_t - r)
        tz = s / c
        g = r - (a + b * tz * tz) * tz  # f(r) = r - R(z_t - r) = 0 defines the refraction r
        dg = dt(1) + (a + dt(3) * b * tz * tz) / (c * c)
        r = r - g / dg
    return r


def zenith_geometry(r: np.ndarray, zenith: np.ndarray):
    """(cos z, sin z, tangential) of unit directions r (N, 3) about the zenith (3,): tangential = U - (r.U) r points
    toward the zenith with length sin z (N, 3)."""
    dt = r.dtype.type
    u = np.asarray(zenith, dtype=r.dtype)
    cz = r @ u
    tangential = u[None, :] - cz[:, None] * r
    sz = np.sqrt(np.maximum(np.sum(tangential * tangential, axis=1), dt(0)))
    return cz, sz, tangential


def rotate_in_vertical(
    r: np.ndarray, sz: np.ndarray, tangential: np.ndarray, angle_rad: np.ndarray, angle_over_sin_z_at_zenith: np.ndarray
) -> np.ndarray:
    """Rotate each r by ``angle_rad`` toward the zenith (negative: away), about the axis r x U, keeping the azimuth:
    r cos(angle) + tangential sin(angle) / sin z. At the zenith itself (sin z = 0) the ratio sin(angle) / sin z is
    the given limit (refraction is proportional to tan z, so the ratio stays finite)."""
    dt = r.dtype.type
    ok = sz > dt(1e-12)
    ratio = np.where(ok, np.sin(angle_rad) / np.where(ok, sz, dt(1)), angle_over_sin_z_at_zenith)
    return np.cos(angle_rad)[:, None] * r + ratio[:, None] * tangential


def refract_toward_zenith(
    r: np.ndarray,
    zenith: np.ndarray,
    weather: Weather,
    model: str = "atan",
    lat_rad: float | None = None,
    true_zenith_argument: bool = False,
) -> np.ndarray:
    """Lift true directions (N, 3) toward the zenith (3,) by the refraction: the apparent directions (N, 3).

    Seed 001 sec. 4 (eq. 22-25: add R to the elevation, keep the azimuth), with R evaluated at the correct argument
    (:func:`refraction_from_true_zenith`). ``true_zenith_argument=True`` instead evaluates the formula at the true
    zenith distance, as seed 001 does (error < 0.1" only up to about 60 deg; for reproducing the paper). Works in any
    frame in which ``zenith`` is given (local north-up-east: (0, 1, 0)). ``lat_rad`` only matters for
    ``model="seed001"`` (eq. 16's gravity term). Dtype of ``r``.
    """
    dt = r.dtype.type
    a, b = model_coefficients(weather, model, lat_rad)
    cz, sz, tangential = zenith_geometry(r, zenith)
    if true_zenith_argument:
        refr = refraction_apparent(cz, sz, a, b)
    else:
        refr = refraction_from_true_zenith(cz, sz, a, b)
    limit = dt(a) / np.maximum(cz, dt(MIN_COS_ZENITH))
    return rotate_in_vertical(r, sz, tangential, refr, limit)


def topocentric_observed(
    r: np.ndarray,
    zenith: np.ndarray,
    site_velocity_m_s: np.ndarray,
    weather: Weather | None = None,
    model: str = "atan",
    lat_rad: float | None = None,
    true_zenith_argument: bool = False,
) -> np.ndarray:
    """Geocentric apparent unit directions r (N, 3) -> the directions observed at a ground site (N, 3), dtype of r.

    1. Diurnal aberration: r + ``aberration_change(r, v / c)`` with v the site's velocity from the Earth's rotation
       (3,) [m/s], in r's frame (``onboard.earth.site_velocity_tod_m_s`` for TOD; in the local north-up-east frame
       it is (0, 0, speed), eastward). The change is computed on its own and added once (full float32 precision).
    2. With ``weather``: refraction by addition toward ``zenith`` (3,) (same frame), :func:`refract_toward_zenith`
       with ``model``, ``lat_rad`` and ``true_zenith_argument`` (seed 001 sec. 4). Without: no atmosphere.
    """
    dt = r.dtype.type
    beta = np.asarray(site_velocity_m_s, dtype=r.dtype) / dt(SPEED_OF_LIGHT_M_S)
    topo = r + aberration_change(r, beta)
    if weather is None:
        return topo
    return refract_toward_zenith(topo, zenith, weather, model, lat_rad, true_zenith_argument)


# ------------------------------------------------------------------------------------------------- fixed point
# The per-star part of :func:`topocentric_observed` in integers, for a sensor without an FPU (the twin of the
# float code above, step by step; formats and their ranges below, bounds in docs/port-kit.md "Fixed-point formats";
# ``tests/test_fixedpoint_refraction.py`` holds it against float64 of the float code). Every shift rounds to nearest
# (``onboard.fixedpoint.rshift_round``); every division rounds to nearest (``fixedpoint.div_round``, divisor > 0).
#
#   quantity                    format   range (why)
#   r, zenith U, result         Q30      unit vectors: |component| <= 2^30 + 1
#   beta = v / c                Q48      |beta| <= 2^-18 (v <= 1143 m/s: a site, a ship, an aircraft): |B_c| <= 2^30
#   r.beta                      Q48      <= 2^30; products Q30 x Q48 <= 2^60, three summed < 2^62
#   A, B                        Q56      |A| <= 2^-10, |B| <= 2^-19 (fixed_refraction refuses more): <= 2^46, 2^37
#   cos z, sin z (clamped)      Q30      cos z >= MIN_COS_ZENITH (the float code's limit), sin z <= 1
#   tan z                       Q24      <= 1 / MIN_COS_ZENITH = 20: < 2^28.4 (numerator sin z 2^54 < 2^63)
#   tan^2 z                     Q16      <= 400: < 2^24.7;  B tan^2 z: 2^37 x 2^24.7 < 2^62
#   A + B tan^2, A + 3 B tan^2  Q56      <= 2^-10 + 3 2^-19 400 < 2^-7.6: < 2^48.4
#   refraction R, Newton g      Q36      |R| <= 20 (2^-10 + 2^-19 400) < 2^-3.9: < 2^32.1; g << 30 < 2^62.2
#   1 + (A + 3 B tan^2) / cos^2 Q30      in [1 - 2^-5, 1 + 2^-0.9]: numerator Q60 < 2^52.4
#   cos R, sin R, sin R / sin z Q30      |R| < 2^-3.9 (series below); sin R / sin z <= (A + B tan^2) / cos z < 2^-3.3
#
# Series: cos R = 1 - R^2/2 + R^4/24 and sin R = R - R^3/6 leave R^6/720 and R^5/120, < 2^-37 at |R| < 2^-3.9.
# The diurnal aberration is first order, beta - (r.beta) r: the relativistic formula of ``aberration_change`` differs
# by at most 1.5 |beta|^2 < 2^-36, and the result's length differs from 1 by |beta|^2 / 2 < 2^-37 (not renormalised).

#: Fractional bits of the site velocity beta = v / c, and its largest magnitude (2^-18 = 1143 m/s).
BETA_FRAC_BITS = 48
MAX_BETA_LOG2 = -18
#: Fractional bits of the refraction coefficients A, B, of the refraction R, of tan z and tan^2 z.
COEF_FRAC_BITS = 56
R_FRAC_BITS = 36
TAN_FRAC_BITS = 24
TAN2_FRAC_BITS = 16
#: Largest |A| and |B| the formats are proved for: 2^-10 rad = 202" (3.4x A at sea level, 0 C), 2^-19 rad.
MAX_A_LOG2 = -10
MAX_B_LOG2 = -19


@dataclass(frozen=True)
class FixedRefraction:
    """A refraction model R = A tan z_a + B tan^3 z_a in the fixed-point formats: A and B in Q56 [rad]. Built once
    per weather (:func:`fixed_refraction`), like the float sensor's (A, B)."""

    a_q56: int
    b_q56: int


def fixed_refraction(weather: Weather, model: str = "atan", lat_rad: float | None = None) -> FixedRefraction:
    """(A, B) of :func:`model_coefficients` in Q56. Raises ``onboard.fixedpoint.FixedRangeError`` when |A| > 2^-10
    or |B| > 2^-19 rad (the formats' range: pressures above ~3400 hPa)."""
    a, b = model_coefficients(weather, model, lat_rad)
    if not (abs(a) <= 2.0**MAX_A_LOG2 and abs(b) <= 2.0**MAX_B_LOG2):
        raise FixedRangeError(f"refraction coefficients A {a:.3g}, B {b:.3g} rad exceed the fixed-point range")
    return FixedRefraction(round(math.ldexp(a, COEF_FRAC_BITS)), round(math.ldexp(b, COEF_FRAC_BITS)))


def beta_q48(site_velocity_m_s: np.ndarray) -> np.ndarray:
    """A site velocity (3,) [m/s] as beta = v / c in Q48 (int64). Raises ``FixedRangeError`` above 2^-18 c."""
    beta = np.asarray(site_velocity_m_s, dtype=np.float64) / SPEED_OF_LIGHT_M_S
    if not (np.all(np.isfinite(beta)) and np.sqrt(np.sum(beta * beta)) <= 2.0**MAX_BETA_LOG2):
        raise FixedRangeError("site velocity above the fixed-point range (2^-18 c = 1143 m/s)")
    return np.rint(np.ldexp(beta, BETA_FRAC_BITS)).astype(np.int64)


def _cos_sin_q30(r_q36):
    """cos R and sin R in Q30 from R in Q36 (|R| < 2^-3.9): the series of the table above."""
    r = rshift_round(r_q36, R_FRAC_BITS - Q)  # Q30, |r| < 2^26.1
    r2 = rshift_round(r * r, Q)  # R^2, Q30 < 2^22.2
    r4 = rshift_round(r2 * r2, Q)  # R^4, Q30
    cos_r = (1 << Q) - rshift_round(r2, 1) + div_round(r4, 24)
    sin_r = r - div_round(rshift_round(r * r2, Q), 6)
    return cos_r, sin_r


def refraction_from_true_zenith_q36(cos_q30, sin_q30, coef: FixedRefraction, steps: int = TRUE_ZENITH_NEWTON_STEPS):
    """R [rad] in Q36 from cos and sin of the true zenith distance (Q30): :func:`refraction_from_true_zenith` step by
    step (Newton on R - A tan(z_t - R) - B tan^3(z_t - R), from R = 0, the rotation of (cos, sin) by R), in
    integers with one division for tan z and one for the Newton step per iteration. Integer-generic: int64 arrays,
    or object arrays of Python integers (the exact reference of the range tests)."""
    min_cos = round(MIN_COS_ZENITH * (1 << Q))
    a, b = coef.a_q56, coef.b_q56
    r = np.zeros_like(cos_q30)
    for _ in range(steps):
        cr, sr = _cos_sin_q30(r)
        c = np.maximum(rshift_round(cos_q30 * cr + sin_q30 * sr, Q), min_cos)  # cos(z_t - R)
        s = rshift_round(sin_q30 * cr - cos_q30 * sr, Q)  # sin(z_t - R)
        tz = div_round(s << TAN_FRAC_BITS, c)  # tan, Q24
        tz2 = rshift_round(tz * tz, 2 * TAN_FRAC_BITS - TAN2_FRAC_BITS)  # Q16
        btz2 = rshift_round(b * tz2, TAN2_FRAC_BITS)  # B tan^2, Q56
        k = a + btz2  # Q56
        f = rshift_round(rshift_round(k, COEF_FRAC_BITS - 40) * tz, 40 + TAN_FRAC_BITS - R_FRAC_BITS)  # Q36
        g = r - f
        c2 = rshift_round(c * c, Q)  # Q30 >= 2^21.4
        dg = (1 << Q) + div_round((a + 3 * btz2) << (2 * Q - COEF_FRAC_BITS), c2)  # Q30: Q60 / Q30
        r = r - div_round(g << Q, dg)
    return r


def topocentric_observed_q30(
    r_q30: np.ndarray, zenith_q30: np.ndarray, beta: np.ndarray, coef: FixedRefraction | None = None
) -> np.ndarray:
    """:func:`topocentric_observed` in integers: geocentric apparent unit vectors (N, 3) Q30 -> as observed at the
    site (N, 3) Q30. ``zenith_q30`` (3,) Q30 and ``beta`` (3,) Q48 (:func:`beta_q48`) in r's frame; ``coef``
    (:func:`fixed_refraction`) or None for no atmosphere.

    1. Diurnal aberration to first order: r + beta - (r.beta) r, in Q48, rounded to Q30 once.
    2. Refraction by addition (seed 001 sec. 4): cos z = r.U, tangential t = U - (r.U) r, sin z = |t| (integer
       square root), R from :func:`refraction_from_true_zenith_q36`, then r cos R + t (sin R / sin z)."""
    r = np.asarray(r_q30)
    beta = np.asarray(beta)
    shift = BETA_FRAC_BITS - Q
    rb = rshift_round(r @ beta, Q)  # r.beta, Q48
    topo = rshift_round((r << shift) + beta[None, :] - rshift_round(rb[:, None] * r, Q), shift)
    if coef is None:
        return topo
    u = np.asarray(zenith_q30)
    cz = rshift_round(topo @ u, Q)  # Q30
    t = u[None, :] - rshift_round(cz[:, None] * topo, Q)  # Q30, |t| = sin z
    sz = isqrt(np.sum(t * t, axis=1))  # Q30 (|t|^2 in Q60 < 2^60.01)
    refr = refraction_from_true_zenith_q36(cz, sz, coef)
    cr, sr = _cos_sin_q30(refr)
    ratio = np.where(sz > 0, div_round(sr << Q, np.maximum(sz, 1)), 0)  # sin R / sin z, Q30 (t = 0 where sz = 0)
    return rshift_round(cr[:, None] * topo + ratio[:, None] * t, Q)


def topocentric_observed_fixed(
    r: np.ndarray,
    zenith: np.ndarray,
    site_velocity_m_s: np.ndarray,
    weather: Weather | None = None,
    model: str = "atan",
    lat_rad: float | None = None,
) -> np.ndarray:
    """:func:`topocentric_observed` as a sensor without an FPU computes it (float64 in and out, for the host's
    emulation of that sensor): r and the zenith quantised to Q30 (its catalogue and its site frame), the velocity
    to Q48 and (A, B) to Q56 once, then :func:`topocentric_observed_q30`. Raises ``FixedRangeError`` outside the
    formats' range."""
    coef = None if weather is None else fixed_refraction(weather, model, lat_rad)
    out = topocentric_observed_q30(quantise_unit_q30(r), quantise_unit_q30(zenith), beta_q48(site_velocity_m_s), coef)
    return np.ldexp(out.astype(np.float64), -Q)
