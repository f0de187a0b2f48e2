"""Host-side geometry of a ground site and ERFA's refraction: the truth the onboard float32 code is tested against.

Frames: every vector here is in the true equator and equinox of date (the frame of the session's reference
directions, ``hostlink.sky.apparent``). Its pole is the CIP, which is the terrestrial pole when polar motion is
ignored (docs/interfaces.md), so the local zenith is the geodetic vertical rotated by the Greenwich apparent sidereal
time.

Refraction: ERFA's model (``erfa.refco``) relates the observed zenith distance ``z_obs`` to the
in-vacuo topocentric one ``z_top`` by ``z_top = z_obs + A tan z_obs + B tan^3 z_obs`` (refco's definition). The
truth here is what pyerfa's observed place (``atioq``/``atco13``) applies: one Newton step of that relation from
``z_top`` (:func:`refraction_truth_rad`), differing from the exact inverse by 3 mas at z = 75 deg and 20 mas at 80 deg,
both far inside the model's own error there. The lift is applied as an exact rotation in the vertical plane (ERFA
uses cos(dz) ~ 1 - dz^2/2, a difference below 0.05 mas at z = 80 deg).
Diurnal aberration (<= 0.32") IS applied (:func:`observed_directions_truth`), before refraction, as ERFA's observed
place does (apco13 adds the site's velocity, from ``erfa.pvtob``, to the Earth's before aberrating; its atioq then
skips its own diurnal step, ``diurab = 0``): here ERFA's ``ab`` aberrates the geocentric apparent direction by the
site velocity alone (:func:`diurnal_aberration_truth`). Applying the two velocities one after the other instead of
their sum differs by O(beta_earth beta_site) = 1e-4 x 1.6e-6 rad = 3e-5"; the first-order formula alone would have
been good to beta_site^2 = 2.4e-12 rad (5e-7"). Geocentric-to-topocentric stellar parallax (< 1e-4", 6400 km at
the nearest star's distance) is NOT applied. So the truth observed direction is the geocentric apparent direction,
aberrated by the site's rotation velocity, then lifted by refraction; tests/test_sky_site.py checks it against
``erfa.atco13`` (ICRS -> observed in one ERFA call) for Hipparcos stars.
"""

from __future__ import annotations

import erfa
import numpy as np

from hostlink.files.times import utc_to_tt, utc_to_ut1
from onboard.site import Site, Weather

#: Largest zenith distance the refraction functions accept [deg]: ERFA's A tan z + B tan^3 z model is meant for
#: z < ~83 deg (refco note 3); ERFA's atioq floors cos z at 0.05 (z = 87.1 deg). The simulator stays below this.
MAX_ZENITH_DISTANCE_DEG = 85.0


def _gast_rad(jd_utc1, jd_utc2, dut1_s: float) -> np.ndarray:
    """Greenwich apparent sidereal time [rad], (F,), from UTC (UT1 = UTC + dut1, TT from UTC; ``erfa.gst06a``)."""
    j1, j2 = np.atleast_1d(np.asarray(jd_utc1, np.float64)), np.atleast_1d(np.asarray(jd_utc2, np.float64))
    ut1 = utc_to_ut1(j1, j2, dut1_s)
    tt = utc_to_tt(j1, j2)
    return np.atleast_1d(np.asarray(erfa.gst06a(ut1[0], ut1[1], tt[0], tt[1])))


def zenith_true_of_date(
    jd_utc1: float | np.ndarray, jd_utc2: float | np.ndarray, site: Site, dut1_s: float = 0.0
) -> np.ndarray:
    """Unit vector of the local (geodetic) zenith in the true equator and equinox of date, (3,) or (F, 3).

    Hour angle of the zenith = GAST + east longitude, GAST from ``erfa.gst06a`` (UT1 = UTC + dut1, TT from UTC);
    declination = geodetic latitude. Polar motion is ignored (docs/interfaces.md).
    """
    scalar = np.ndim(jd_utc1) == 0 and np.ndim(jd_utc2) == 0
    theta = _gast_rad(jd_utc1, jd_utc2, dut1_s) + np.radians(site.lon_deg)
    phi = np.radians(site.lat_deg)
    z = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.full_like(theta, np.sin(phi))], axis=-1)
    return z[0] if scalar else z


def site_velocity_true_of_date(
    jd_utc1: float | np.ndarray, jd_utc2: float | np.ndarray, site: Site, dut1_s: float = 0.0
) -> np.ndarray:
    """The site's velocity from the Earth's rotation [m/s], true equator and equinox of date, (3,) or (F, 3).

    ``erfa.pvtob`` (WGS84 site position, Earth rotation rate 1.00273781191135448 turns per UT1 day, polar motion
    and TIO locator 0) with the Greenwich apparent sidereal time as its rotation angle: ERFA rotates the terrestrial
    frame by that angle about the pole, which lands in the true-of-date frame as ``zenith_true_of_date`` does.
    Eastward, 465 m/s cos(lat) at sea level.
    """
    scalar = np.ndim(jd_utc1) == 0 and np.ndim(jd_utc2) == 0
    gast = _gast_rad(jd_utc1, jd_utc2, dut1_s)
    pv = erfa.pvtob(np.radians(site.lon_deg), np.radians(site.lat_deg), float(site.height_m), 0.0, 0.0, 0.0, gast)
    vel = np.asarray(np.atleast_1d(pv)["v"], dtype=np.float64).reshape(-1, 3)
    return vel[0] if scalar else vel


def local_north_east(zenith: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors toward local north and east, same shape as ``zenith`` ((3,) or (F, 3)), true of date.

    North is the celestial pole (0, 0, 1) projected on the horizon plane; east = north x zenith, so (east, north,
    zenith) is right-handed and azimuth runs from north through east. Undefined at the geographic poles.
    """
    z = np.asarray(zenith, dtype=np.float64)
    pole = np.zeros_like(z)
    pole[..., 2] = 1.0
    north = pole - np.sum(pole * z, axis=-1, keepdims=True) * z
    north = north / np.linalg.norm(north, axis=-1, keepdims=True)
    east = np.cross(north, z)
    return north, east


def refraction_constants(weather: Weather) -> tuple[float, float]:
    """ERFA's A and B [rad] of dz = A tan z + B tan^3 z for the weather (``erfa.refco``)."""
    refa, refb = erfa.refco(weather.pressure_hpa, weather.temp_c, weather.rel_humidity, weather.wavelength_um)
    return float(refa), float(refb)


def _check_zenith_distance(z_rad: np.ndarray) -> None:
    if np.any(~np.isfinite(z_rad)) or np.any(z_rad < 0) or np.any(z_rad > np.radians(MAX_ZENITH_DISTANCE_DEG)):
        raise ValueError(f"zenith distance outside [0, {MAX_ZENITH_DISTANCE_DEG}] deg: refraction model not valid")


def refraction_observed_rad(observed_zenith_distance_rad: np.ndarray, weather: Weather) -> np.ndarray:
    """Refraction [rad] at an OBSERVED zenith distance: A tan z + B tan^3 z (ERFA refco's model definition)."""
    z = np.asarray(observed_zenith_distance_rad, dtype=np.float64)
    _check_zenith_distance(z)
    refa, refb = refraction_constants(weather)
    t = np.tan(z)
    return refa * t + refb * t**3


def refraction_truth_rad(zenith_distance_rad: np.ndarray, weather: Weather) -> np.ndarray:
    """Refraction [rad] of a star at the given UNREFRACTED (topocentric, in vacuo) zenith distance z: the amount by
    which it appears lifted toward the zenith, exactly as ERFA's ``atioq`` (and so ``atco13``) computes it: one
    Newton step of z = z_obs + A tan z_obs + B tan^3 z_obs from z_obs = z,
    dz = (A + B tan^2 z) tan z / (1 + (A + 3 B tan^2 z) sec^2 z)."""
    z = np.asarray(zenith_distance_rad, dtype=np.float64)
    _check_zenith_distance(z)
    refa, refb = refraction_constants(weather)
    t = np.tan(z)
    w = refb * t * t
    return (refa + w) * t / (1.0 + (refa + 3.0 * w) * (1.0 + t * t))


def zenith_distance_rad(r: np.ndarray, zenith: np.ndarray) -> np.ndarray:
    """Zenith distance [rad] of directions r (N, 3) given the zenith (3,) or one per row (N, 3), by atan2 (accurate
    at every angle)."""
    r = np.asarray(r, dtype=np.float64)
    z = np.broadcast_to(np.asarray(zenith, dtype=np.float64), r.shape)
    cos_z = np.sum(r * z, axis=-1)
    sin_z = np.linalg.norm(np.cross(z, r), axis=-1)
    return np.arctan2(sin_z, cos_z)


def refract_directions_truth(r: np.ndarray, zenith: np.ndarray, weather: Weather) -> np.ndarray:
    """Observed (refracted) unit directions (N, 3): each apparent direction r rotated toward the zenith (3,) or
    (N, 3), in its vertical plane, by :func:`refraction_truth_rad` of its zenith distance."""
    r = np.asarray(r, dtype=np.float64)
    z = np.broadcast_to(np.asarray(zenith, dtype=np.float64), r.shape)
    zd = zenith_distance_rad(r, z)
    dz = refraction_truth_rad(zd, weather)
    # unit vector in the vertical plane, perpendicular to r, pointing up; at the zenith itself refraction is zero
    up = z - np.sum(r * z, axis=-1, keepdims=True) * r
    norm = np.linalg.norm(up, axis=-1, keepdims=True)
    up = np.divide(up, norm, out=np.zeros_like(up), where=norm > 0)
    return np.cos(dz)[:, None] * r + np.sin(dz)[:, None] * up


#: Distance to the Sun [AU] passed to ``erfa.ab`` to switch off its light-deflection potential term: that term is
#: part of the geocentric apparent place already, the diurnal step adds only the site's velocity.
_NO_POTENTIAL_AU = 1e100


def diurnal_aberration_truth(r: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
    """Geocentric apparent unit directions r (N, 3) -> topocentric (N, 3), aberrated by the site's velocity (3,) or
    (N, 3) [m/s] in r's frame: ``erfa.ab`` (relativistic; the velocity alone, see the module docstring)."""
    r = np.asarray(r, dtype=np.float64)
    beta = np.broadcast_to(np.asarray(velocity_m_s, dtype=np.float64) / erfa.CMPS, r.shape)
    bm1 = np.sqrt(1.0 - np.sum(beta * beta, axis=-1))
    return np.asarray(erfa.ab(r, beta, _NO_POTENTIAL_AU, bm1))


def observed_directions_truth(
    r: np.ndarray, zenith: np.ndarray, velocity_m_s: np.ndarray, weather: Weather | None
) -> np.ndarray:
    """What a ground sensor sees (N, 3): geocentric apparent directions r (N, 3) aberrated by the site velocity
    ((3,) or (N, 3) [m/s], :func:`site_velocity_true_of_date`), then, with weather, refracted toward the zenith
    ((3,) or (N, 3)) by :func:`refract_directions_truth`. Without weather (no atmosphere) only the aberration."""
    topo = diurnal_aberration_truth(r, velocity_m_s)
    return topo if weather is None else refract_directions_truth(topo, zenith, weather)
