"""Issue 5 acceptance: on a ground session at zenith distances of 5-75 deg, refraction correction takes the boresight
error from tens of arcseconds RMS uncorrected to under 0.7" RMS, and to the Cramer-Rao floor of the same frames.

The session is the real sky (Hipparcos, apparent place and refraction from ERFA in ``hostlink.sky.simulate``) through
seed 004's camera (hostlink/data/seed004_camera.json, 8.4 deg field) with 0.05 px centroid noise; the attitude is
``hostlink.commands.attitude.solve_session``, the code behind ``hostlink attitude``.

Whether 0.7" is reachable is a matter of star count, not of the correction: the floor for 0.05 px is about
0.85" / sqrt(n / 10.7). Measured (400 frames each, float64, reference correction / floor):
- Hp <= 6.0, at least 5 stars (10.7 stars/frame, seed 1): 0.848" vs a floor of 0.853" (0.99x); 100" uncorrected.
  Under 0.7" is impossible there at 0.05 px; the earlier 0.895" against 0.85" was such a session (1.05x).
- Hp <= 6.5, at least 10 stars (18.4-19.4 stars/frame, seeds 0-3): 0.598-0.630" vs 0.601-0.618" (0.99-1.02x).
- Hp <= 7.0, at least 10 stars (27.7 stars/frame): 0.45-0.50" vs 0.485" (0.93-1.02x).
"""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.commands.attitude import solve_session
from hostlink.sky.simulate import SimConfig, simulate
from onboard import attitude as att
from onboard.camera import pixels_to_unit
from onboard.params import params_from_dict
from onboard.site import Site, Weather

ARCSEC = np.pi / 648000.0
SITE = Site(39.9, 116.4, 50.0)
WEATHER = Weather(10.0, 1013.25, 0.5)
NOISE_PX = 0.05
#: 400 frames: the RMS of 800 boresight components scatters by 1/sqrt(2 * 800) = 2.5% about the floor.
FRAMES = 400
#: Corrected RMS / floor: 1.15 is 6 standard deviations of the 400-frame scatter above 1 (measured 0.99-1.03x);
#: a residual systematic error of 0.35" (half the noise) would already exceed it.
FLOOR_FACTOR = 1.15
ACCEPTANCE_ARCSEC = 0.7


def _camera():
    import json

    from hostlink.sky.simulate import data_file

    return params_from_dict(json.loads(data_file("seed004_camera.json").read_text()))


@pytest.fixture(scope="module")
def sessions():
    cam = _camera()
    out = {}
    # typical (15-30 stars) and the 10.7-star session of the earlier measurement
    for name, maglim, min_stars, seed in (("hp6.5", 6.5, 10, 0), ("hp6.0", 6.0, 5, 1)):
        cfg = SimConfig(camera=cam, frames=FRAMES, noise_px=NOISE_PX, min_stars=min_stars, max_stars=30,
                        maglim=maglim, seed=seed, site=SITE, weather=WEATHER, zenith_range_deg=(5.0, 75.0))
        out[name] = simulate(cfg)
    return cam, out


def _boresight_rms_arcsec(c, c_true) -> float:
    a, b = np.asarray(c[:, 2, :], dtype=np.float64), c_true[:, 2, :]
    err = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))
    return float(np.sqrt(np.mean(err**2))) / ARCSEC


def _boresight_floor_arcsec(session, cam) -> float:
    """RMS over frames of the per-frame Cramer-Rao bound of the boresight error (rotations about sensor x and y),
    for isotropic direction noise of NOISE_PX / F rad (seed 004's 8.4 deg field: the pixel scale varies by < 0.3%)."""
    theta = cam.model_vector(np.float64)
    sigma_rad = NOISE_PX / cam.focal_length_px
    var = [np.trace(att.attitude_covariance(pixels_to_unit(session.x_px[sl], session.y_px[sl], theta),
                                            sigma_rad)[:2, :2]) for sl in session.frame_slices()]
    return float(np.sqrt(np.mean(var))) / ARCSEC


def _rms_by_mode(sim, cam, dtype):
    c_true = sim.attitude
    rms = {}
    for mode in ("none", "reference", "observed"):
        cols = solve_session(sim.session, cam, SITE, WEATHER, 0.0, mode, dtype=dtype)
        assert np.all(cols["status"] == "ok")
        rms[mode] = _boresight_rms_arcsec(cols["C"], c_true)
    return rms


def test_typical_session_has_15_to_30_stars_per_frame(sessions):
    _, sims = sessions
    s = sims["hp6.5"].session
    counts = np.diff(s.frame_starts)
    assert 15 <= np.median(counts) <= 30 and counts.min() >= 10  # the session the acceptance is stated for


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_refraction_correction_brings_a_ground_session_under_0p7_arcsec_at_the_noise_floor(sessions, dtype):
    cam, sims = sessions
    sim = sims["hp6.5"]
    floor = _boresight_floor_arcsec(sim.session, cam)
    rms = _rms_by_mode(sim, cam, dtype)
    # uncorrected: refraction of 5-75 deg (1' at 45 deg) tilts the whole field: 95" RMS measured
    assert 30.0 < rms["none"] < 300.0
    for mode in ("reference", "observed"):
        assert rms[mode] < ACCEPTANCE_ARCSEC
        assert rms[mode] < FLOOR_FACTOR * floor


def test_a_10p7_star_session_sits_at_its_floor_which_is_above_0p7_arcsec(sessions):
    cam, sims = sessions
    sim = sims["hp6.0"]
    assert 10.0 < len(sim.session) / sim.session.n_frames < 11.5
    floor = _boresight_floor_arcsec(sim.session, cam)
    rms = _rms_by_mode(sim, cam, "float64")
    assert floor > ACCEPTANCE_ARCSEC  # 0.853": with ~10.7 stars at 0.05 px, 0.7" cannot be reached by any method
    assert rms["none"] > 30.0
    for mode in ("reference", "observed"):
        assert rms[mode] < FLOOR_FACTOR * floor
