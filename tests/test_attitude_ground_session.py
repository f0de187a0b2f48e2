"""Issue 5 acceptance: on a ground session at zenith distances of 5-75 deg, refraction correction takes the boresight
error from tens of arcseconds RMS uncorrected to under 0.7" RMS, and to the Cramer-Rao floor of the same frames.

The session is the real sky (Hipparcos, apparent place, diurnal aberration and refraction from ERFA in
``hostlink.sky.simulate``, checked against erfa.atco13 to 1e-4") through seed 004's camera
(hostlink/data/seed004_camera.json, 8.4 deg field) with 0.05 px centroid noise; the attitude is
``hostlink.sky.attitude.solve_attitudes``, the code behind ``hostlink attitude`` (with --site it always applies
the diurnal aberration of the site's rotation to the reference directions, ``onboard.refraction.topocentric_observed``).

Whether 0.7" is reachable is a matter of star count, not of the correction: the floor for 0.05 px is about
0.85" / sqrt(n / 10.7). Measured (400 frames each, float64; float32 within 0.001"; uncorrected = ``none`` /
reference correction / the same without the diurnal term / floor):
- Hp <= 6.0, at least 5 stars (10.7 stars/frame, seed 1): 100" / 0.848" / 0.872" / 0.853" (0.99x; 1.02x without
  the diurnal term). Under 0.7" is impossible there at 0.05 px.
- Hp <= 6.5, at least 10 stars (18.4-18.7 stars/frame, seeds 0-1): 95-100" / 0.613" / 0.638-0.644" / 0.614-0.617"
  (0.99-1.00x; 1.04x without).
- Hp <= 7.0, at least 10 stars (27.6 stars/frame, seed 0): 95" / 0.488" / 0.524" / 0.484" (1.01x; 1.08x without).
The observed-quantity method gives the same to 0.001" (both reject on corrected vectors). Without the diurnal
term every boresight misses by the site's aberration (slope -0.87 to -1.00 of the predicted shift, 0.17-0.19" on
average at 39.9 deg, 0.25" at most): a bias that adds to the noise in quadrature and that, unlike the noise, no
number of stars removes.
"""

from __future__ import annotations

import numpy as np
import pytest
from attitude_bounds import attitude_covariance

from hostlink.sky.attitude import solve_attitudes
from hostlink.sky.simulate import SimConfig, simulate
from hostlink.sky.site import site_velocity_true_of_date
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

    from hostlink.files.params import data_file

    return params_from_dict(json.loads(data_file("seed004_camera.json").read_text()))


@pytest.fixture(scope="module")
def sessions():
    cam = _camera()
    out = {}
    # typical (15-30 stars) and the 10.7-star session of the earlier measurement
    for name, maglim, min_stars, seed in (("hp6.5", 6.5, 10, 0), ("hp6.0", 6.0, 5, 1)):
        cfg = SimConfig(
            camera=cam,
            frames=FRAMES,
            noise_px=NOISE_PX,
            min_stars=min_stars,
            max_stars=30,
            maglim=maglim,
            seed=seed,
            site=SITE,
            weather=WEATHER,
            zenith_range_deg=(5.0, 75.0),
        )
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
    var = [
        np.trace(attitude_covariance(pixels_to_unit(session.x_px[sl], session.y_px[sl], theta), sigma_rad)[:2, :2])
        for sl in session.frame_slices()
    ]
    return float(np.sqrt(np.mean(var))) / ARCSEC


def _rms_by_mode(sim, cam, dtype):
    c_true = sim.attitude
    rms = {}
    for mode in ("none", "reference", "observed"):
        cols = solve_attitudes(sim.session, cam, SITE, WEATHER, 0.0, mode, dtype=dtype)
        assert np.all(cols.status == "ok")
        rms[mode] = _boresight_rms_arcsec(cols.C, c_true)
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


def _boresight_shift_along_diurnal(c, sim) -> tuple[float, float]:
    """(slope, mean shift [arcsec]) of the estimated-minus-true boresight u projected on each frame's predicted
    diurnal shift d = beta - (beta . u) u (beta = site velocity / c from ERFA's pvtob, independent of the code under
    test): slope = sum (du . d) / sum |d|^2 is -1 when the attitude ignores the aberration (the estimated boresight
    moves away from the apex), 0 when it is corrected; the mean shift is the same along d in arcseconds."""
    jd1, jd2 = sim.session.frame_times_jd()
    beta = site_velocity_true_of_date(jd1, jd2, SITE) / 299792458.0
    u = sim.attitude[:, 2, :]
    d = beta - np.sum(beta * u, axis=1)[:, None] * u
    du = np.asarray(c[:, 2, :], dtype=np.float64) - u
    along = np.sum(du * d, axis=1)
    return float(np.sum(along) / np.sum(d * d)), float(np.mean(along / np.linalg.norm(d, axis=1))) / ARCSEC


def test_without_the_diurnal_term_the_attitude_carries_the_site_aberration_and_with_it_none(sessions):
    _, sims = sessions
    sim = sims["hp6.5"]
    for mode in ("reference", "observed"):
        with_it = solve_attitudes(sim.session, _camera(), SITE, WEATHER, 0.0, mode)
        without = solve_attitudes(sim.session, _camera(), SITE, WEATHER, 0.0, mode, diurnal_aberration=False)
        slope_with, shift_with = _boresight_shift_along_diurnal(with_it.C, sim)
        slope_without, shift_without = _boresight_shift_along_diurnal(without.C, sim)
        # the noise of the slope: 0.6" / sqrt(2) per axis / sqrt(400 frames) over a 0.2" shift = 0.11; 0.4 is 3.7 sd
        # (measured: -0.94 / -0.95 without, +0.06 / +0.05 with, seed 0)
        assert abs(slope_without + 1.0) < 0.4
        assert abs(slope_with) < 0.4
        # a 0.2" bias at 39.9 deg (site speed 357 m/s: 0.25" at most, 0.2" on average across the boresight); the
        # mean shift's noise is 0.022", so 0.1" separates the two by 4.5 sd either side (measured -0.19" / +0.01")
        assert -0.3 < shift_without < -0.1
        assert abs(shift_with) < 0.1


def test_reference_and_observed_methods_agree_within_0p1_arcsec_frame_by_frame(sessions):
    # seed 001 sec. 5 / Table 8: the two corrections agree within 0.1"; the diurnal term is on the reference side of
    # both, so it must not open a gap between them, and both keep the same stars (measured: 0.005" boresight,
    # 0.013" about it, at most over 400 frames)
    cam, sims = sessions
    sim = sims["hp6.5"]
    ref = solve_attitudes(sim.session, cam, SITE, WEATHER, 0.0, "reference")
    obs = solve_attitudes(sim.session, cam, SITE, WEATHER, 0.0, "observed")
    np.testing.assert_array_equal(ref.n_used, obs.n_used)
    a, b = ref.C, obs.C
    gap = np.linalg.norm(np.cross(a, b), axis=2) / ARCSEC  # each sensor axis, (frames, 3)
    assert gap.max() < 0.1
