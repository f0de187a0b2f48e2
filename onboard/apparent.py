"""Apparent place of catalogue stars on the sensor: proper motion, parallax, light deflection by the Sun, annual
(and the observer's own) aberration, then precession-nutation to the true equator and equinox of date.

Returns unit vectors in the TOD frame (true equator and equinox of date, see :mod:`onboard.earth`): the frame of the
session file's ``ra_deg, dec_deg``. (ERFA's ``atci13`` returns CIRS; RA_tod = RA_cirs - EO, with EO from ``eo06a``.)
The pipeline is that of ERFA's atciq (pmpx, ldsun, ab, then the precession-nutation rotation), the Earth's
barycentric state coming from :func:`earth_barycentric_state`, a compact model (Keplerian Earth-Moon barycentre,
circular Moon, the Sun's reflex motion about the barycentre due to Jupiter and Saturn), good to 4 m/s in velocity
(0.003" of aberration) and 0.003 AU in position over 2000-2050 against ERFA epv00.

Seed 000 sec. 3 (eq. 14-18) lists the same steps with IAU 1976 precession and first-order aberration; those cannot
reach 0.1", hence IAU 2006 precession, a 30-term nutation and the relativistic aberration formula here.

The onboard catalogue stores unit vectors and space-motion vectors (:func:`catalogue_vectors`, run once when the
catalogue is built, in float64, then stored in the sensor's dtype): a float32 right ascension in radians is only
good to 0.1".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.earth import ARCSEC_TO_RAD, true_of_date_matrix
from onboard.fixedpoint import FixedRangeError, Q, div_round, normalise_q30, quantise_unit_q30, rshift_round
from onboard.timescale import (
    DAYS_PER_JULIAN_CENTURY,
    DAYS_PER_JULIAN_YEAR,
    FixedTime,
    days_since_j2000,
)

#: Speed of light [m/s] and the astronomical unit [m] (IAU 2012).
SPEED_OF_LIGHT_M_S = 299792458.0
ASTRONOMICAL_UNIT_M = 149597870700.0
#: Light time for 1 AU [day].
AU_LIGHT_TIME_DAY = ASTRONOMICAL_UNIT_M / SPEED_OF_LIGHT_M_S / 86400.0
#: 2 G M_sun / (c^2 AU): the Sun's light deflection at 1 AU [rad] (Schwarzschild radius / AU).
SUN_DEFLECTION_RAD = 1.97412574336e-8
#: Mean obliquity of J2000 (IAU 2006) [rad], ecliptic -> equator of the orbit model.
_EPS0_RAD = 84381.406 * ARCSEC_TO_RAD
#: Hipparcos catalogue epoch J1991.25 and J2000.0, as Julian years.
EPOCH_HIPPARCOS_JYEAR = 1991.25
EPOCH_J2000_JYEAR = 2000.0

#: Mean Keplerian elements, J2000 ecliptic and equinox (Standish, "Keplerian elements for approximate positions of
#: the major planets", JPL, Table 1, 1800-2050): a [AU], e, I [deg], L [deg], varpi [deg], Omega [deg], each with its
#: rate per Julian century.
_ELEMENTS = {
    "emb": (
        (1.00000261, 0.00000562),
        (0.01671123, -0.00004392),
        (-0.00001531, -0.01294668),
        (100.46457166, 35999.37244981),
        (102.93768193, 0.32327364),
        (0.0, 0.0),
    ),
    "jupiter": (
        (5.20288700, -0.00011607),
        (0.04838624, -0.00013253),
        (1.30439695, -0.00183714),
        (34.39644051, 3034.74612775),
        (14.72847983, 0.21252668),
        (100.47390909, 0.20469106),
    ),
    "saturn": (
        (9.53667594, -0.00125060),
        (0.05386179, -0.00050991),
        (2.48599187, 0.00193609),
        (49.95424423, 1222.49362201),
        (92.59887831, -0.41897216),
        (113.66242448, -0.28867794),
    ),
}
#: Planet / Sun mass ratios (IAU 2009 / DE405): the Sun's reflex about the solar-system barycentre.
_MASS_RATIO = {"jupiter": 1.0 / 1047.3486, "saturn": 1.0 / 3497.898}
#: Moon / (Earth + Moon) mass ratio, the Moon's mean longitude (deg, deg per century; Simon et al. 1994) and mean
#: distance [AU]: the Earth's offset from the Earth-Moon barycentre (a circular orbit; 12 m/s, 4700 km).
_MOON_MASS_FRACTION = 1.0 / 82.30057
_MOON_LONGITUDE_DEG = (218.3164477, 481267.88123421)
_MOON_DISTANCE_AU = 384400e3 / ASTRONOMICAL_UNIT_M
#: Kepler's equation: Newton iterations from E = M (e < 0.06 needs 3 for 1e-12; a fixed count keeps the cost bounded).
_KEPLER_ITERATIONS = 4


def catalogue_vectors(ra_rad, dec_rad, pm_ra_cosdec_mas_yr, pm_dec_mas_yr, dtype=np.float32):
    """Catalogue rows -> (unit vectors (N, 3), proper-motion vectors (N, 3) [rad/yr]) in ``dtype``.

    ``pm_ra_cosdec`` is mu_alpha* = mu_alpha cos(dec) (the Hipparcos convention). Evaluated in float64 and then cast:
    this is the catalogue-building step, not a per-frame one.
    """
    ra = np.asarray(ra_rad, dtype=np.float64)
    dec = np.asarray(dec_rad, dtype=np.float64)
    k = 1e-3 * ARCSEC_TO_RAD
    pa = np.asarray(pm_ra_cosdec_mas_yr, dtype=np.float64) * k
    pd = np.asarray(pm_dec_mas_yr, dtype=np.float64) * k
    ca, sa, cd, sd = np.cos(ra), np.sin(ra), np.cos(dec), np.sin(dec)
    r = np.stack([cd * ca, cd * sa, sd], axis=-1)
    e_ra = np.stack([-sa, ca, np.zeros_like(ca)], axis=-1)
    e_dec = np.stack([-sd * ca, -sd * sa, cd], axis=-1)
    pm = pa[..., None] * e_ra + pd[..., None] * e_dec
    return r.astype(dtype), pm.astype(dtype)


def _ecliptic_to_equatorial(v: np.ndarray) -> np.ndarray:
    """J2000 ecliptic -> J2000 equatorial (GCRS axes; the 0.02" frame bias is far below the model's accuracy)."""
    dt = v.dtype.type
    c, s = dt(np.cos(_EPS0_RAD)), dt(np.sin(_EPS0_RAD))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([x, c * y - s * z, s * y + c * z], axis=-1)


def _kepler_state(elements, t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heliocentric position [AU] and velocity [AU/day] on a Keplerian orbit with linearly varying mean elements,
    J2000 ecliptic axes."""
    dt = t_c.dtype.type
    (a0, a1), (e0, e1), (i0, i1), (l0, l1), (w0, w1), (o0, o1) = elements
    deg = dt(np.pi / 180.0)
    a = dt(a0) + dt(a1) * t_c
    e = dt(e0) + dt(e1) * t_c
    inc = (dt(i0) + dt(i1) * t_c) * deg
    big_l = np.mod(dt(l0) + dt(l1) * t_c, dt(360.0)) * deg
    varpi = (dt(w0) + dt(w1) * t_c) * deg
    node = (dt(o0) + dt(o1) * t_c) * deg
    mean_motion = dt(l1) * deg / dt(DAYS_PER_JULIAN_CENTURY)  # rad/day
    m = big_l - varpi
    ecc_anom = m
    for _ in range(_KEPLER_ITERATIONS):
        ecc_anom = ecc_anom - (ecc_anom - e * np.sin(ecc_anom) - m) / (dt(1) - e * np.cos(ecc_anom))
    ce, se = np.cos(ecc_anom), np.sin(ecc_anom)
    root = np.sqrt(dt(1) - e * e)
    x, y = a * (ce - e), a * root * se
    edot = mean_motion / (dt(1) - e * ce)
    vx, vy = -a * se * edot, a * root * ce * edot
    argp = varpi - node
    cw, sw, co, so, ci, si = np.cos(argp), np.sin(argp), np.cos(node), np.sin(node), np.cos(inc), np.sin(inc)
    # orbital plane -> ecliptic: R3(-node) R1(-inc) R3(-argp)
    p = np.stack([co * cw - so * sw * ci, so * cw + co * sw * ci, sw * si], axis=-1)
    q = np.stack([-co * sw - so * cw * ci, -so * sw + co * cw * ci, cw * si], axis=-1)
    return x[..., None] * p + y[..., None] * q, vx[..., None] * p + vy[..., None] * q


def earth_barycentric_state(t_tt: FixedTime, dtype=np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Earth's barycentric position [AU], barycentric velocity [AU/day] and heliocentric position [AU], GCRS axes.

    Compact model: EMB Keplerian (Standish), Earth = EMB - m_moon/(m_E + m_M) r_moon (circular lunar orbit in the
    ecliptic), Sun's barycentric offset = -sum (m_p / M_sun) r_p for Jupiter and Saturn (Keplerian). Accuracy over
    2000-2050 against ERFA epv00: 4 m/s in velocity, 0.003 AU in position (tests/test_apparent_*).
    """
    t_c = days_since_j2000(t_tt, dtype) / np.dtype(dtype).type(DAYS_PER_JULIAN_CENTURY)
    dt = t_c.dtype.type
    emb_p, emb_v = _kepler_state(_ELEMENTS["emb"], t_c)
    moon_lon = np.mod(dt(_MOON_LONGITUDE_DEG[0]) + dt(_MOON_LONGITUDE_DEG[1]) * t_c, dt(360.0)) * dt(np.pi / 180.0)
    moon_rate = dt(_MOON_LONGITUDE_DEG[1] * np.pi / 180.0 / DAYS_PER_JULIAN_CENTURY)
    k = dt(_MOON_MASS_FRACTION * _MOON_DISTANCE_AU)
    zero = np.zeros_like(moon_lon)
    earth_off_p = -k * np.stack([np.cos(moon_lon), np.sin(moon_lon), zero], axis=-1)
    earth_off_v = -k * moon_rate * np.stack([-np.sin(moon_lon), np.cos(moon_lon), zero], axis=-1)
    helio_p = emb_p + earth_off_p
    helio_v = emb_v + earth_off_v
    sun_p = np.zeros_like(helio_p)
    sun_v = np.zeros_like(helio_v)
    for planet, ratio in _MASS_RATIO.items():
        pp, pv = _kepler_state(_ELEMENTS[planet], t_c)
        sun_p = sun_p - dt(ratio) * pp
        sun_v = sun_v - dt(ratio) * pv
    return (
        _ecliptic_to_equatorial(helio_p + sun_p),
        _ecliptic_to_equatorial(helio_v + sun_v),
        _ecliptic_to_equatorial(helio_p),
    )


def _normalise(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.sum(v * v, axis=-1, keepdims=True))


# Each correction returns a *change* of the direction, not a new direction: the changes are small (< 1e-2), so they
# carry full relative precision in float32 and are added to the catalogue vector once, at the end (one rounding of
# a unit vector, 0.01", instead of one per step). Each change is evaluated at the direction accumulated so far, so
# cross terms (aberration of a star that moved 600" since the catalogue epoch) are kept.


def space_motion_change(
    r0: np.ndarray, pm_rad_yr: np.ndarray, parallax_mas, years: np.ndarray, earth_bary_au: np.ndarray
) -> np.ndarray:
    """Proper motion and parallax (ERFA pmpx without the Roemer term; seed 000 eq. 14 in vector form):
    years * pm - plx E_b, to be added to r0 (the sum is not yet unit length: later steps are insensitive to a
    1e-5 scale error, and the end result is normalised). Radial velocity is taken as zero."""
    dt = r0.dtype.type
    plx = np.asarray(parallax_mas, dtype=r0.dtype) * dt(1e-3 * ARCSEC_TO_RAD)
    return years * pm_rad_yr - plx[..., None] * earth_bary_au


def deflection_change(p: np.ndarray, earth_helio_au: np.ndarray) -> np.ndarray:
    """Light deflection by the Sun (ERFA ld with q = p, the star at infinity): (2GM/c^2 |E|) (e - (p.e) p) /
    (1 + p.e), e the unit Sun->Earth vector. 0.004" at 90 deg from the Sun, 0.05" at 10 deg."""
    dt = p.dtype.type
    dist = np.sqrt(np.sum(earth_helio_au * earth_helio_au))
    e = earth_helio_au / dist
    pe = p @ e
    # keep the denominator away from zero for a star behind the Sun (ERFA uses the same kind of limit)
    denom = np.maximum(1 + pe, dt(1e-6))
    k = dt(SUN_DEFLECTION_RAD) / dist
    return (k / denom)[..., None] * (e - pe[..., None] * p)


def aberration_change(p: np.ndarray, velocity_c: np.ndarray) -> np.ndarray:
    """Relativistic aberration (ERFA ab without its 1e-12 potential term), velocity in units of c: the proper
    direction is (bm1 p + w1 v) / (1 + p.v), w1 = 1 + p.v / (1 + bm1), bm1 = sqrt(1 - v^2); the change is
    (w1 v - (p.v + v^2 / (1 + bm1)) p) / (1 + p.v), using bm1 - 1 = -v^2 / (1 + bm1) to avoid cancellation."""
    dt = p.dtype.type
    v = velocity_c.astype(p.dtype)
    v2 = np.sum(v * v)
    bm1 = np.sqrt(dt(1) - v2)
    pv = p @ v
    one = dt(1)
    w1 = one + pv / (one + bm1)
    return (w1[..., None] * v - (pv + v2 / (one + bm1))[..., None] * p) / (one + pv)[..., None]


def apparent_place_vectors(
    r0: np.ndarray,
    pm_rad_yr: np.ndarray,
    parallax_mas,
    epoch_jyear: float,
    t_tt: FixedTime,
    observer_velocity_gcrs_m_s=None,
) -> np.ndarray:
    """Catalogue vectors (``catalogue_vectors``) -> apparent directions in TOD (N, 3), computed in r0's dtype.

    ``t_tt``: one instant (TT; UTC is 0.001" close). ``epoch_jyear``: the catalogue epoch (1991.25 for Hipparcos,
    2000.0 for J2000 catalogues). ``observer_velocity_gcrs_m_s``: the sensor's velocity relative to the geocentre,
    GCRS axes [m/s] (orbital aberration; a ground site's rotation velocity gives diurnal aberration); None = the
    geocentre (geocentric apparent place, as ERFA atci13).
    """
    dtype = r0.dtype
    dt = dtype.type
    earth_p, earth_v, earth_h = earth_barycentric_state(t_tt, dtype)
    years = days_since_j2000(t_tt, dtype) / dt(DAYS_PER_JULIAN_YEAR) + dt(EPOCH_J2000_JYEAR - epoch_jyear)
    change = space_motion_change(r0, pm_rad_yr, parallax_mas, years, earth_p)
    change = change + deflection_change(r0 + change, earth_h)
    v_c = earth_v * dt(AU_LIGHT_TIME_DAY)
    if observer_velocity_gcrs_m_s is not None:
        v_c = v_c + np.asarray(observer_velocity_gcrs_m_s, dtype=dtype) / dt(SPEED_OF_LIGHT_M_S)
    change = change + aberration_change(_normalise(r0 + change), v_c)
    return _normalise(r0 + change) @ true_of_date_matrix(t_tt, dtype).T


def apparent_place(
    ra_rad,
    dec_rad,
    pm_ra_cosdec_mas_yr,
    pm_dec_mas_yr,
    parallax_mas,
    epoch_jyear: float,
    t_tt: FixedTime,
    observer_velocity_gcrs_m_s=None,
    dtype=np.float32,
) -> np.ndarray:
    """Catalogue rows (ICRS RA/Dec [rad] at ``epoch_jyear``, mu_alpha* and mu_delta [mas/yr], parallax [mas]) ->
    apparent unit vectors in TOD, shape (N, 3), dtype ``dtype``. See :func:`apparent_place_vectors`."""
    r0, pm = catalogue_vectors(ra_rad, dec_rad, pm_ra_cosdec_mas_yr, pm_dec_mas_yr, dtype)
    plx = np.asarray(parallax_mas, dtype=dtype)
    return apparent_place_vectors(r0, pm, plx, epoch_jyear, t_tt, observer_velocity_gcrs_m_s)


# ------------------------------------------------------------------------------------------------- fixed point
# The per-star part of :func:`apparent_place_vectors` in integers, for a sensor without an FPU (its twin, step by
# step; docs/port-kit.md "Fixed-point formats"; ``tests/test_fixedpoint_apparent.py`` holds it against float64 of the
# float code). The per-instant part (the Earth's state, the GCRS -> TOD matrix: once per frame, not per star) runs in
# soft float64 (:func:`fixed_instant`) and is quantised once. Every shift and division rounds to nearest.
#
#   quantity                         format  range (why)
#   r0, Sun->Earth unit e, result    Q30     unit vectors; the GCRS -> TOD matrix M: |M_ij| <= 1
#   proper motion pm [rad/yr]        Q46     |pm| <= 2^-14 rad/yr (12.6"/yr; Barnard's star 10.4"/yr): < 2^32
#   years since the catalogue epoch  Q20     |years| <= 2^7: < 2^27; years pm: Q66 < 2^59
#   parallax [rad]                   Q48     <= 2^-17 rad (1.57"; Proxima 0.77"): < 2^31
#   Earth barycentric E_b [AU]       Q30     < 1.02 AU < 2^0.03; parallax E_b: Q78 < 2^61.1
#   space motion change c1           Q48     <= 2^7 2^-14 + 2^-17 1.02 < 2^-6.9: < 2^41.1
#   k = 2 G M / (c^2 |E_h|) [rad]    Q70     <= 1.97e-8 / 0.983 < 2^-25.5: < 2^44.5
#   1 + p.e (clamped at 2^-5)        Q30     stars >= 14.4 deg from the Sun (a star tracker's Sun exclusion is wider)
#   k / (1 + p.e)                    Q48     <= 2^-20.5: < 2^27.5 (numerator k << 8 < 2^52.5)
#   velocity beta = v / c            Q44     |beta| <= 2^-13 (36.6 km/s: the Earth's 30 km/s and an orbit's 8)
#   p.beta, beta^2                   Q44     < 2^31, < 2^18; products Q30 x Q44 < 2^61, three summed < 1.5 2^62
#
# Aberration to second order: from (w1 v - (p.v + v^2 / (1 + bm1)) p) / (1 + p.v) (``aberration_change``),
# change = v - (p.v / 2) v - (p.v - (p.v)^2 + v^2 / 2) p, leaving terms of order |beta|^3 < 2^-38 (1/256 Q30 step).

#: Fractional bits of the formats above.
PM_FRAC_BITS = 46
YEARS_FRAC_BITS = 20
PARALLAX_FRAC_BITS = 48
CHANGE_FRAC_BITS = 48
DEFLECTION_K_FRAC_BITS = 70
ABERRATION_BETA_FRAC_BITS = 44
#: 1 + p.e is clamped at 2^-5 in Q30 (stars >= 14.4 deg from the Sun are exact).
MIN_ONE_PLUS_PE_Q30 = 1 << 25
#: Largest magnitudes the formats take (checked by :func:`fixed_catalogue` and :func:`fixed_instant`).
MAX_PM_RAD_YR = 2.0**-14
MAX_YEARS = 2.0**7
MAX_PARALLAX_RAD = 2.0**-17
MAX_BETA = 2.0**-13


@dataclass(frozen=True)
class FixedInstant:
    """What :func:`apparent_place_vectors_q30` needs of one instant, in the fixed formats (module table)."""

    years_q20: int
    earth_bary_q30: np.ndarray  # (3,) AU
    sun_to_earth_q30: np.ndarray  # (3,) unit
    deflection_k_q70: int
    beta_q44: np.ndarray  # (3,)
    tod_q30: np.ndarray  # (3, 3) GCRS -> TOD


def fixed_catalogue(r0: np.ndarray, pm_rad_yr: np.ndarray, parallax_mas) -> tuple[np.ndarray, ...]:
    """Catalogue vectors (float64, :func:`catalogue_vectors`) -> (r0 Q30, pm Q46, parallax Q48 rad), once, when the
    catalogue is built. Raises ``FixedRangeError`` for a proper motion above 2^-14 rad/yr or a parallax above 2^-17
    rad."""
    pm = np.asarray(pm_rad_yr, dtype=np.float64)
    plx = np.asarray(parallax_mas, dtype=np.float64) * (1e-3 * ARCSEC_TO_RAD)
    if not (np.all(np.sqrt(np.sum(pm * pm, axis=-1)) <= MAX_PM_RAD_YR) and np.all(np.abs(plx) <= MAX_PARALLAX_RAD)):
        raise FixedRangeError("proper motion or parallax above the fixed-point range (2^-14 rad/yr, 2^-17 rad)")
    return (
        quantise_unit_q30(r0),
        np.rint(np.ldexp(pm, PM_FRAC_BITS)).astype(np.int64),
        np.rint(np.ldexp(plx, PARALLAX_FRAC_BITS)).astype(np.int64),
    )


def fixed_instant(t_tt: FixedTime, epoch_jyear: float, observer_velocity_gcrs_m_s=None) -> FixedInstant:
    """The per-instant quantities of :func:`apparent_place_vectors` (soft float64 on the sensor, once per frame), in
    the fixed formats. Raises ``FixedRangeError`` outside them (more than 128 years from the catalogue epoch, a
    velocity above 2^-13 c)."""
    f64 = np.float64
    earth_p, earth_v, earth_h = earth_barycentric_state(t_tt, f64)
    years = float(days_since_j2000(t_tt, f64)) / DAYS_PER_JULIAN_YEAR + (EPOCH_J2000_JYEAR - epoch_jyear)
    v_c = earth_v * AU_LIGHT_TIME_DAY
    if observer_velocity_gcrs_m_s is not None:
        v_c = v_c + np.asarray(observer_velocity_gcrs_m_s, dtype=f64) / SPEED_OF_LIGHT_M_S
    if not (abs(years) <= MAX_YEARS and np.sqrt(np.sum(v_c * v_c)) <= MAX_BETA):
        raise FixedRangeError("instant or velocity outside the fixed-point range (128 years, 2^-13 c)")
    dist = float(np.sqrt(np.sum(earth_h * earth_h)))
    return FixedInstant(
        years_q20=round(math.ldexp(years, YEARS_FRAC_BITS)),
        earth_bary_q30=quantise_unit_q30(earth_p),
        sun_to_earth_q30=quantise_unit_q30(earth_h / dist),
        deflection_k_q70=round(math.ldexp(SUN_DEFLECTION_RAD / dist, DEFLECTION_K_FRAC_BITS)),
        beta_q44=np.rint(np.ldexp(v_c, ABERRATION_BETA_FRAC_BITS)).astype(np.int64),
        tod_q30=quantise_unit_q30(true_of_date_matrix(t_tt, f64)),
    )


def apparent_place_vectors_q30(r0_q30, pm_q46, parallax_q48, inst: FixedInstant):
    """:func:`apparent_place_vectors` in integers: catalogue vectors (N, 3) Q30, proper motions (N, 3) Q46 [rad/yr],
    parallaxes (N,) Q48 [rad] -> apparent directions in TOD (N, 3) Q30. Space motion, light deflection, aberration
    (second order) as changes in Q48 added to r0, normalised by the integer reciprocal square root, then rotated by
    the Q30 matrix. Integer-generic (int64, or Python integers in object arrays)."""
    up = CHANGE_FRAC_BITS - Q  # Q30 -> Q48
    r0 = np.asarray(r0_q30)
    # space motion: years pm - parallax E_b (Q48)
    c1 = rshift_round(inst.years_q20 * np.asarray(pm_q46), YEARS_FRAC_BITS + PM_FRAC_BITS - CHANGE_FRAC_BITS)
    c1 = c1 - rshift_round(np.asarray(parallax_q48)[:, None] * inst.earth_bary_q30[None, :], Q)
    # light deflection at p = r0 + c1: k (e - (p.e) p) / (1 + p.e) (Q48)
    p = rshift_round((r0 << up) + c1, up)  # Q30
    e = inst.sun_to_earth_q30
    pe = rshift_round(p @ e, Q)  # Q30
    one_pe = np.maximum((1 << Q) + pe, MIN_ONE_PLUS_PE_Q30)
    q = div_round(inst.deflection_k_q70 << (CHANGE_FRAC_BITS + Q - DEFLECTION_K_FRAC_BITS), one_pe)  # Q78 / Q30
    c2 = c1 + rshift_round(q[:, None] * (e[None, :] - rshift_round(pe[:, None] * p, Q)), Q)
    # aberration at the normalised direction, second order (module table), Q44
    p = normalise_q30(rshift_round((r0 << up) + c2, up))
    v = inst.beta_q44
    vb = ABERRATION_BETA_FRAC_BITS
    pv = rshift_round(p @ v, Q)
    v2 = rshift_round(v @ v, vb)
    m = pv - rshift_round(pv * pv, vb) + rshift_round(v2, 1)
    ab = v[None, :] - rshift_round(pv[:, None] * v[None, :], vb + 1) - rshift_round(m[:, None] * p, Q)
    c3 = c2 + (ab << (CHANGE_FRAC_BITS - vb))
    # normalise, then rotate to the true equator and equinox of date
    p = normalise_q30(rshift_round((r0 << up) + c3, up))
    return rshift_round(p @ inst.tod_q30.T, Q)
