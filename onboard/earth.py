"""Earth orientation for the sensor: precession-nutation, Earth rotation, sidereal time and the local frame.

Frames (every function says which it returns):
- GCRS: geocentric, ICRS axes (the catalogue's frame after apparent-place corrections up to aberration).
- TOD: the true equator and equinox of date (the session file's ``ra_deg, dec_deg`` frame, docs/file-formats.md);
  ``r_tod = N P B r_gcrs`` (:func:`true_of_date_matrix`). ERFA's CIRS right ascension relates by RA_tod = RA_cirs - EO.
- Local (seed 001 eq. 9, 22): north-up-east, ``x`` north, ``y`` up (the zenith), ``z`` east; ``r_local = R_ig r_tod``
  (:func:`local_frame_matrix`). Polar motion and the deflection of the vertical are ignored (docs/file-formats.md).

Earth rotation is computed in fixed point: angles as 64-bit binary angles (a full turn is 2^64, so unsigned
wrap-around *is* the modulo), and only the final sine and cosine are taken in the working dtype, after an exact
quadrant reduction, so a float32 sensor keeps 0.01" where a float32 angle in radians would lose 0.1" and a float32
Julian date hundreds of arcseconds.

Sources: ERA, IAU 2000 (IERS Conventions 2010 eq. 5.15); GMST, IAU 2006 (Capitaine, Wallace & Chapront 2005;
IERS 2010 eq. 5.32); precession, IAU 2006 Fukushima-Williams angles (Capitaine & Wallace 2006; IERS 2010 eq. 5.40,
frame bias included); nutation, the IAU 2000B luni-solar series (McCarthy & Luzum 2003, Cel. Mech. 85, 37) truncated
to its 30 largest terms (0.006" pole, 0.014" in longitude against IAU 2000A over 2000-2050), with its fixed offsets
in lieu of planetary terms; equation of equinoxes with its two largest complementary terms (IERS 2010 Table 5.2e).
"""

from __future__ import annotations

import numpy as np

from onboard.site import Site
from onboard.timescale import (
    DEFAULT_TAI_MINUS_UTC_S,
    FixedTime,
    julian_centuries,
    tt_from_utc,
    ut1_from_utc,
)

ARCSEC_TO_RAD = np.pi / 648000.0
_TURN = 1 << 64
_TWO_PI = 2.0 * np.pi

#: ERA = 2 pi (0.7790572732640 + 1.00273781191135448 Du), Du = JD(UT1) - 2451545.0 (IERS 2010 eq. 5.15), as binary
#: angles: the constant, the rate's fractional part per day, and that rate >> 32 for the 2^-32-day fraction.
_ERA0_BAM = np.uint64(round(0.7790572732640 * _TURN))
_ERA_RATE_BAM_PER_DAY = np.uint64(round(0.00273781191135448 * _TURN))
_ERA_RATE_BAM_PER_FRAC = np.uint64(int(_ERA_RATE_BAM_PER_DAY) >> 32)

#: Earth's rotation rate [rad/s] (IERS 2010), for the site's velocity (diurnal aberration).
EARTH_ROTATION_RAD_S = 7.292115146706979e-5
#: GRS80 / WGS84 ellipsoid, for the site's distance from the Earth's axis.
EARTH_EQUATORIAL_RADIUS_M = 6378137.0
EARTH_FLATTENING = 1.0 / 298.257223563

#: IAU 2006 Fukushima-Williams angles gamma_bar, phi_bar, psi_bar, eps_A [arcsec], coefficients of t^0..t^5 (t in
#: Julian centuries TT since J2000); IERS Conventions 2010 eq. 5.40 and eq. 5.39 (eps_A).
_FW_GAMMA_AS = (-0.052928, 10.556378, 0.4932044, -0.00031238, -0.000002788, 0.0000000260)
_FW_PSI_AS = (-0.041775, 5038.481484, 1.5584175, -0.00018522, -0.000026452, -0.0000000148)
#: phi_bar and eps_A are kept as offsets from the J2000 obliquity eps_0 = 84381.406" (IAU 2006), so float32 carries
#: their small parts at full precision (phi_bar = 84381.412819" - 46.811016" t + ...; eps_A = 84381.406" - ...).
_EPS0_AS = 84381.406
_FW_PHI_MINUS_EPS0_AS = (0.006819, -46.811016, 0.0511268, 0.00053289, -0.000000440, -0.0000000176)
_EPS_A_MINUS_EPS0_AS = (0.0, -46.836769, -0.0001831, 0.00200340, -0.000000576, -0.0000000434)
#: GMST - ERA [arcsec], IAU 2006 (IERS 2010 eq. 5.32).
_GMST_MINUS_ERA_AS = (0.014506, 4612.156534, 1.3915817, -0.00000044, -0.000029956, -0.0000000368)

#: Delaunay arguments l, l', F, D, Omega [arcsec]: constant and rate per Julian century (Simon et al. 1994, as used
#: by IAU 2000B).
_DELAUNAY_AS = np.array(
    [
        (485868.249036, 1717915923.2178),
        (1287104.79305, 129596581.0481),
        (335779.526232, 1739527262.8478),
        (1072260.70369, 1602961601.2090),
        (450160.398036, -6962890.5431),
    ],
    dtype=np.float64,
)
#: IAU 2000B luni-solar nutation, its 30 largest terms (McCarthy & Luzum 2003, Table 2; the order of the published
#: table). Columns: multipliers of l, l', F, D, Omega; dpsi sin, t sin, cos; deps cos, t cos, sin [0.1 uas].
_NUTATION_TERMS = np.array(
    [
        (0, 0, 0, 0, 1, -172064161, -174666, 33386, 92052331, 9086, 15377),
        (0, 0, 2, -2, 2, -13170906, -1675, -13696, 5730336, -3015, -4587),
        (0, 0, 2, 0, 2, -2276413, -234, 2796, 978459, -485, 1374),
        (0, 0, 0, 0, 2, 2074554, 207, -698, -897492, 470, -291),
        (0, 1, 0, 0, 0, 1475877, -3633, 11817, 73871, -184, -1924),
        (0, 1, 2, -2, 2, -516821, 1226, -524, 224386, -677, -174),
        (1, 0, 0, 0, 0, 711159, 73, -872, -6750, 0, 358),
        (0, 0, 2, 0, 1, -387298, -367, 380, 200728, 18, 318),
        (1, 0, 2, 0, 2, -301461, -36, 816, 129025, -63, 367),
        (0, -1, 2, -2, 2, 215829, -494, 111, -95929, 299, 132),
        (0, 0, 2, -2, 1, 128227, 137, 181, -68982, -9, 39),
        (-1, 0, 2, 0, 2, 123457, 11, 19, -53311, 32, -4),
        (-1, 0, 0, 2, 0, 156994, 10, -168, -1235, 0, 82),
        (1, 0, 0, 0, 1, 63110, 63, 27, -33228, 0, -9),
        (-1, 0, 0, 0, 1, -57976, -63, -189, 31429, 0, -75),
        (-1, 0, 2, 2, 2, -59641, -11, 149, 25543, -11, 66),
        (1, 0, 2, 0, 1, -51613, -42, 129, 26366, 0, 78),
        (-2, 0, 2, 0, 1, 45893, 50, 31, -24236, -10, 20),
        (0, 0, 0, 2, 0, 63384, 11, -150, -1220, 0, 29),
        (0, 0, 2, 2, 2, -38571, -1, 158, 16452, -11, 68),
        (0, -2, 2, -2, 2, 32481, 0, 0, -13870, 0, 0),
        (-2, 0, 0, 2, 0, -47722, 0, -18, 477, 0, -25),
        (2, 0, 2, 0, 2, -31046, -1, 131, 13238, -11, 59),
        (1, 0, 2, -2, 2, 28593, 0, -1, -12338, 10, -3),
        (-1, 0, 2, 0, 1, 20441, 21, 10, -10758, 0, -3),
        (2, 0, 0, 0, 0, 29243, 0, -74, -609, 0, 13),
        (0, 0, 2, 0, 0, 25887, 0, -66, -550, 0, 11),
        (0, 1, 0, 0, 1, -14053, -25, 79, 8551, -2, -45),
        (-1, 0, 0, 2, 1, 15164, 10, 11, -8001, 0, -1),
        (0, 2, 2, -2, 2, -15794, 72, -16, 6850, -42, -5),
    ],
    dtype=np.int64,
)
#: IAU 2000B fixed offsets in lieu of the planetary terms (dpsi, deps) [arcsec] (Luzum 2001, as in ERFA nut00b).
_NUTATION_PLANETARY_OFFSET_AS = (-0.000135, 0.000388)
_UAS01_TO_AS = 1e-7


# --------------------------------------------------------------------------------------------------- binary angles


def bam_from_turns(turns: float) -> np.uint64:
    """A configuration constant in turns (Python float, e.g. longitude / 360) -> 64-bit binary angle."""
    return np.uint64(int(round((turns % 1.0) * _TURN)) % _TURN)


def bam_from_small_rad(angle_rad: np.ndarray) -> np.ndarray:
    """A small floating angle (|x| < 2^31 * 2 pi) -> binary angle, at 2^-32-turn resolution (0.0003")."""
    angle_rad = np.asarray(angle_rad)
    units = np.rint(angle_rad * angle_rad.dtype.type(float(1 << 32) / _TWO_PI)).astype(np.int64)
    return (units << np.int64(32)).astype(np.uint64)


def bam_sincos(bam: np.ndarray, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """(sin, cos) of a binary angle in ``dtype``, with an exact quadrant reduction first (so the floating argument is
    within +-pi/4 and a float32 result is good to 6e-8, 0.012")."""
    b = np.atleast_1d(np.asarray(bam, dtype=np.uint64))
    quadrant = ((b + np.uint64(1 << 61)) >> np.uint64(62)) & np.uint64(3)
    rest = (b - (quadrant << np.uint64(62))).view(np.int64)
    x = rest.astype(np.dtype(dtype)) * np.dtype(dtype).type(_TWO_PI / _TURN)
    s, c = np.sin(x), np.cos(x)
    q = quadrant.astype(np.int64)
    sin_out = np.where(q == 0, s, np.where(q == 1, c, np.where(q == 2, -s, -c)))
    cos_out = np.where(q == 0, c, np.where(q == 1, -s, np.where(q == 2, -c, s)))
    shape = np.shape(bam)
    return sin_out.reshape(shape), cos_out.reshape(shape)


def bam_to_rad(bam: np.ndarray) -> np.ndarray:
    """Binary angle -> float64 radians in [0, 2 pi) (host-side diagnostics and tests)."""
    return np.asarray(bam, dtype=np.uint64).astype(np.float64) * (_TWO_PI / _TURN)


# --------------------------------------------------------------------------------------------------- Earth rotation


def earth_rotation_angle_bam(t_ut1: FixedTime) -> np.ndarray:
    """Earth rotation angle as a 64-bit binary angle (IERS 2010 eq. 5.15), exact integer arithmetic.

    ERA = 2 pi (0.7790572732640 + frac(Du) + 0.00273781191135448 Du): the whole turns of 1.0 * Du drop out, the
    day count multiplies the rate modulo 2^64 and the day fraction is already a binary fraction of a turn.
    """
    day = np.atleast_1d(t_ut1.day).astype(np.int64).view(np.uint64)
    frac = np.atleast_1d(t_ut1.frac).astype(np.uint64)
    with np.errstate(over="ignore"):
        bam = _ERA0_BAM + day * _ERA_RATE_BAM_PER_DAY + (frac << np.uint64(32)) + frac * _ERA_RATE_BAM_PER_FRAC
    return bam.reshape(np.shape(t_ut1.day))


def _poly(coeffs: tuple[float, ...], t: np.ndarray) -> np.ndarray:
    """Horner evaluation of sum c_k t^k in the dtype of ``t``."""
    acc = t * t.dtype.type(0) + t.dtype.type(coeffs[-1])
    for c in coeffs[-2::-1]:
        acc = acc * t + t.dtype.type(c)
    return acc


def precession_offsets(t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IAU 2006 Fukushima-Williams angles as (gamma_bar, phi_bar - eps_0, psi_bar, eps_A - eps_0) [rad], GCRS-based
    (frame bias included), for ``t_c`` Julian centuries TT since J2000 (IERS 2010 eq. 5.39-5.40)."""
    k = t_c.dtype.type(ARCSEC_TO_RAD)
    return (
        _poly(_FW_GAMMA_AS, t_c) * k,
        _poly(_FW_PHI_MINUS_EPS0_AS, t_c) * k,
        _poly(_FW_PSI_AS, t_c) * k,
        _poly(_EPS_A_MINUS_EPS0_AS, t_c) * k,
    )


def precession_angles(t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IAU 2006 Fukushima-Williams angles (gamma_bar, phi_bar, psi_bar, eps_A) [rad] (ERFA pfw06)."""
    gamb, dphi, psib, deps_a = precession_offsets(t_c)
    eps0 = t_c.dtype.type(_EPS0_AS * ARCSEC_TO_RAD)
    return gamb, dphi + eps0, psib, deps_a + eps0


def delaunay_arguments(t_c: np.ndarray) -> np.ndarray:
    """Delaunay arguments (l, l', F, D, Omega) [rad] reduced to [0, 2 pi), shape t_c.shape + (5,)."""
    dt = t_c.dtype.type
    t = np.asarray(t_c)[..., None]
    c0 = _DELAUNAY_AS[:, 0].astype(t_c.dtype)
    rate = _DELAUNAY_AS[:, 1].astype(t_c.dtype)
    return np.mod(c0 + rate * t, dt(1296000.0)) * dt(ARCSEC_TO_RAD)


def nutation(t_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nutation in longitude and obliquity (dpsi, deps) [rad], truncated IAU 2000B (see module docstring)."""
    dt = t_c.dtype.type
    args = delaunay_arguments(t_c)
    mult = _NUTATION_TERMS[:, :5].astype(t_c.dtype)
    coef = _NUTATION_TERMS[:, 5:].astype(t_c.dtype)
    phase = args @ mult.T  # (..., terms)
    s, c = np.sin(phase), np.cos(phase)
    t = np.asarray(t_c)[..., None]
    dpsi = np.sum((coef[:, 0] + coef[:, 1] * t) * s + coef[:, 2] * c, axis=-1)
    deps = np.sum((coef[:, 3] + coef[:, 4] * t) * c + coef[:, 5] * s, axis=-1)
    k = dt(_UAS01_TO_AS * ARCSEC_TO_RAD)
    return (
        dpsi * k + dt(_NUTATION_PLANETARY_OFFSET_AS[0] * ARCSEC_TO_RAD),
        deps * k + dt(_NUTATION_PLANETARY_OFFSET_AS[1] * ARCSEC_TO_RAD),
    )


def rot_x(angle_rad, dtype=np.float32) -> np.ndarray:
    """Frame rotation about x by ``angle_rad`` (ERFA's Rx convention: [[1,0,0],[0,c,s],[0,-s,c]])."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]], dtype=dtype)


def rot_y(angle_rad, dtype=np.float32) -> np.ndarray:
    """Frame rotation about y ([[c,0,-s],[0,1,0],[s,0,c]])."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=dtype)


def rot_z(angle_rad, dtype=np.float32) -> np.ndarray:
    """Frame rotation about z ([[c,s,0],[-s,c,0],[0,0,1]])."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], dtype=dtype)


def true_of_date_matrix(t_tt: FixedTime, dtype=np.float32) -> np.ndarray:
    """NPB (3, 3): GCRS -> true equator and equinox of date, ``r_tod = NPB @ r_gcrs`` (one instant).

    Fukushima-Williams form NPB = R1(-(eps_A + deps)) R3(-(psi_bar + dpsi)) R1(phi_bar) R3(gamma_bar)
    (IERS 2010 eq. 5.41 with nutation added to psi_bar and eps_A), evaluated as
    R1(-(eps_A - eps_0 + deps)) [R1(-eps_0) R3(-(psi_bar + dpsi)) R1(eps_0)] R1(phi_bar - eps_0) R3(gamma_bar):
    rotations about one axis commute, and conjugating by the same rounded eps_0 keeps float32 rounding of the
    84381" obliquity out of the result.
    """
    t_c = julian_centuries(t_tt, dtype)
    gamb, dphi, psib, deps_a = precession_offsets(t_c)
    dpsi, deps = nutation(t_c)
    eps0 = rot_x(np.dtype(dtype).type(_EPS0_AS * ARCSEC_TO_RAD), dtype)
    return (
        rot_x(-(deps_a + deps), dtype)
        @ (eps0.T @ rot_z(-(psib + dpsi), dtype) @ eps0)
        @ rot_x(dphi, dtype)
        @ rot_z(gamb, dtype)
    )


def equation_of_equinoxes(t_c: np.ndarray) -> np.ndarray:
    """GAST - GMST [rad]: dpsi cos eps_A plus the complementary terms 2.64096 mas sin Om + 0.06352 mas sin 2 Om
    (IERS 2010 eq. 5.35, Table 5.2e; the omitted ones are below 0.012 mas)."""
    dt = t_c.dtype.type
    _, _, _, epsa = precession_angles(t_c)  # cos(eps_A) only: float32 rounding of eps_A is harmless here
    dpsi, _ = nutation(t_c)
    om = delaunay_arguments(t_c)[..., 4]
    ct = (dt(0.00264096) * np.sin(om) + dt(0.00006352) * np.sin(dt(2) * om)) * dt(ARCSEC_TO_RAD)
    return dpsi * np.cos(epsa) + ct


def sidereal_time_bam(
    t_ut1: FixedTime, t_tt: FixedTime, east_longitude_deg: float = 0.0, apparent: bool = True, dtype=np.float32
) -> np.ndarray:
    """Greenwich (or local, with a longitude) apparent sidereal time as a binary angle.

    GAST = ERA + (GMST - ERA)(t_TT) + EE(t_TT) (IERS 2010 eq. 5.32, 5.35); ``apparent=False`` gives mean sidereal
    time. The small terms are evaluated in ``dtype`` and added in fixed point.
    """
    t_c = julian_centuries(t_tt, dtype)
    small = _poly(_GMST_MINUS_ERA_AS, t_c) * t_c.dtype.type(ARCSEC_TO_RAD)
    if apparent:
        small = small + equation_of_equinoxes(t_c)
    with np.errstate(over="ignore"):
        return earth_rotation_angle_bam(t_ut1) + bam_from_small_rad(small) + bam_from_turns(east_longitude_deg / 360.0)


def local_frame_from_sidereal(last_bam: np.ndarray, lat_deg: float, dtype=np.float32) -> np.ndarray:
    """R_ig (3, 3): TOD -> local north-up-east (seed 001 eq. 9, 20, 22), rows N, U, E, from local apparent sidereal
    time (binary angle) and geodetic latitude."""
    s_t, c_t = bam_sincos(last_bam, dtype)
    phi = np.dtype(dtype).type(np.deg2rad(lat_deg))
    s_p, c_p = np.sin(phi), np.cos(phi)
    zero = np.zeros_like(s_t)
    return np.array(
        [
            [-s_p * c_t, -s_p * s_t, c_p],  # north
            [c_p * c_t, c_p * s_t, s_p],  # up (zenith)
            [-s_t, c_t, zero],  # east
        ],
        dtype=dtype,
    )


def local_frame_matrix(
    t_utc: FixedTime, site: Site, dut1_s: float = 0.0, tai_minus_utc_s: int = DEFAULT_TAI_MINUS_UTC_S, dtype=np.float32
) -> np.ndarray:
    """R_ig (3, 3): TOD -> local north-up-east at the site, ``r_local = R_ig @ r_tod``, from UTC (one instant),
    the site and dUT1 (UT1 = UTC + dUT1)."""
    last = sidereal_time_bam(
        ut1_from_utc(t_utc, dut1_s), tt_from_utc(t_utc, tai_minus_utc_s), site.lon_deg, dtype=dtype
    )
    return local_frame_from_sidereal(last, site.lat_deg, dtype)


def zenith_true_of_date(
    t_utc: FixedTime, site: Site, dut1_s: float = 0.0, tai_minus_utc_s: int = DEFAULT_TAI_MINUS_UTC_S, dtype=np.float32
) -> np.ndarray:
    """The site's zenith (geodetic normal) as a TOD unit vector (3,): the U row of :func:`local_frame_matrix`."""
    return local_frame_matrix(t_utc, site, dut1_s, tai_minus_utc_s, dtype)[1]


def site_velocity_tod_m_s(
    t_utc: FixedTime, site: Site, dut1_s: float = 0.0, tai_minus_utc_s: int = DEFAULT_TAI_MINUS_UTC_S, dtype=np.float32
) -> np.ndarray:
    """The site's velocity from Earth rotation, TOD axes [m/s] (3,): omega x r, eastward, omega (N + h) cos(phi)
    with N the ellipsoid's prime-vertical radius (GRS80). Feed it (rotated to GCRS) to the apparent place as the
    observer's velocity to include diurnal aberration (0.32" cos(phi) at most)."""
    phi = np.deg2rad(site.lat_deg)
    e2 = EARTH_FLATTENING * (2.0 - EARTH_FLATTENING)
    n_m = EARTH_EQUATORIAL_RADIUS_M / np.sqrt(1.0 - e2 * np.sin(phi) ** 2)
    speed = np.dtype(dtype).type(EARTH_ROTATION_RAD_S * (n_m + site.height_m) * np.cos(phi))
    east = local_frame_matrix(t_utc, site, dut1_s, tai_minus_utc_s, dtype)[2]
    return east * speed
