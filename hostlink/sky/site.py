"""Host-side geometry of a ground site and ERFA's refraction: the truth the onboard float32 code is tested against.

Frames: every vector here is in the true equator and equinox of date (the frame of the session's reference
directions, ``hostlink.sky.apparent``). Its pole is the CIP, which is the terrestrial pole when polar motion is
ignored (INTERFACES.md), so the local zenith is the geodetic vertical rotated by the Greenwich apparent sidereal time.

Refraction: ERFA's model (``erfa.refco``) relates the observed zenith distance ``z_obs`` to the
in-vacuo topocentric one ``z_top`` by ``z_top = z_obs + A tan z_obs + B tan^3 z_obs`` (refco's definition). The
truth here is what pyerfa's observed place (``atioq``/``atco13``) applies: one Newton step of that relation from
``z_top`` (:func:`refraction_truth_rad`), differing from the exact inverse by 3 mas at z = 75 deg and 20 mas at 80 deg,
both far inside the model's own error there. The lift is applied as an exact rotation in the vertical plane (ERFA
uses cos(dz) ~ 1 - dz^2/2, a difference below 0.05 mas at z = 80 deg).
Diurnal aberration (<= 0.32") and geocentric-to-topocentric stellar parallax (< 1e-4") are NOT applied: the truth
observed direction is the geocentric apparent direction lifted by refraction.
"""

from __future__ import annotations

import erfa
import numpy as np

from hostlink.timeutil import utc_to_tt, utc_to_ut1
from onboard.site import Site, Weather

#: Largest zenith distance the refraction functions accept [deg]: ERFA's A tan z + B tan^3 z model is meant for
#: z < ~83 deg (refco note 3); ERFA's atioq floors cos z at 0.05 (z = 87.1 deg). The simulator stays below this.
MAX_ZENITH_DISTANCE_DEG = 85.0


def zenith_true_of_date(
    jd_utc1: float | np.ndarray, jd_utc2: float | np.ndarray, site: Site, dut1_s: float = 0.0
) -> np.ndarray:
    """Unit vector of the local (geodetic) zenith in the true equator and equinox of date, (3,) or (F, 3).

    Hour angle of the zenith = GAST + east longitude, GAST from ``erfa.gst06a`` (UT1 = UTC + dut1, TT from UTC);
    declination = geodetic latitude. Polar motion is ignored (INTERFACES.md).
    """
    scalar = np.ndim(jd_utc1) == 0 and np.ndim(jd_utc2) == 0
    j1, j2 = np.atleast_1d(np.asarray(jd_utc1, np.float64)), np.atleast_1d(np.asarray(jd_utc2, np.float64))
    ut1 = utc_to_ut1(j1, j2, dut1_s)
    tt = utc_to_tt(j1, j2)
    theta = np.asarray(erfa.gst06a(ut1[0], ut1[1], tt[0], tt[1])) + np.radians(site.lon_deg)
    phi = np.radians(site.lat_deg)
    z = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.full_like(theta, np.sin(phi))],
                 axis=-1)
    return z[0] if scalar else z


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
