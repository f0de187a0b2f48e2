"""The principal point with decentering and thin prism free (docs/calibration.md, "Principal point with decentering
and prism free"): the shift that moves no star to first order, the degeneracy line that says so, and the stated
1-sigma of the principal point against the spread of fits to simulated sessions of the real set's geometry."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.calibration.bundle import BundleOptions, bundle_adjust
from hostlink.calibration.mirror import mirror_report, mirrored_principal_point, prism_shift_direction
from hostlink.calibration.model import observation_residuals
from hostlink.calibration.passes import frame_attitudes
from hostlink.calibration.report import degeneracies
from hostlink.calibration.run import calibrate
from hostlink.calibration.synthetic import seed004_true_camera, synthetic_session
from onboard.params import ESTIMATE_NAMES, params_from_dict

#: The granasat camera of docs/realsky.md (~27 x 20 deg, 1280 x 960 px), distortion-free: the nominal of the real
#: set whose fits ended 160 px apart.
GRANASAT = params_from_dict(
    {
        "focal_length_mm": 12.35658,
        "pixel_pitch_um": 4.65,
        "principal_point_px": [666, 440],
        "image_size_px": [1280, 960],
        "distortion": {k: 0.0 for k in ("k1", "k2", "k3", "p1", "p2", "s1", "s2")},
    }
)
#: Decentering and prism held: the remedy the degeneracy line suggests.
WITHOUT_PRISM = ("f", "x0", "y0", "k1", "k2", "k3")


def _rms_after_attitudes_px(data, theta: np.ndarray) -> float:
    """RMS residual length at the camera ``theta`` with every frame's attitude re-fitted (least squares)."""
    att = frame_attitudes(data, theta)
    e = observation_residuals(data.x_px, data.y_px, data.r, np.repeat(att, data.counts, axis=0), theta)
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


@pytest.mark.parametrize("axis", [0, 1])
def test_the_prism_shift_moves_no_star_to_first_order(axis):
    # Finite differences of the model itself: along prism_shift_direction the stars move as d^2 (doubling d
    # quadruples the RMS), a bare principal-point shift moves them as d (doubling it doubles the RMS). Noise-free
    # stars at the truth, so the RMS at d = 0 is rounding (~1e-13 px).
    ss = synthetic_session(GRANASAT, 9, (100, 100), noise_px=0.0, seed=1)
    theta = GRANASAT.model_vector(np.float64)
    step = prism_shift_direction(axis, float(theta[0]))
    bare = np.zeros(10)
    bare[1 + axis] = 1.0
    combined = [_rms_after_attitudes_px(ss.data, theta + d * step) for d in (5.0, 10.0)]
    alone = [_rms_after_attitudes_px(ss.data, theta + d * bare) for d in (5.0, 10.0)]
    # third-order terms (d^3 / F^2 against d^2 / F: ~d / F = 0.4 % at 10 px) are what the 2 % allows for
    assert combined[1] / combined[0] == pytest.approx(4.0, rel=0.02)
    assert alone[1] / alone[0] == pytest.approx(2.0, rel=0.02)
    # and at 10 px the combined shift moves the stars 40 times less than the bare one (0.0045 vs 0.18 px seen)
    assert combined[1] < alone[1] / 20.0


def test_the_degeneracy_line_says_the_principal_point_is_not_determined_with_prism_free():
    # The real set's geometry: 9 frames of the 27 x 20 deg camera, ~600 stars each, 0.3 px noise.
    ss = synthetic_session(GRANASAT, 9, (560, 630), noise_px=0.3, seed=3)
    res = bundle_adjust(ss.data, GRANASAT, BundleOptions(estimate=ESTIMATE_NAMES), screen=False)
    deg = degeneracies(res.normal, res.estimate, res.normal_u_diag)
    found = {p["parameter"]: p for p in deg["principal_point_prism"]}
    assert set(found) == {"x0", "y0"}
    assert found["y0"]["with"] == ["p2", "s2"]
    assert any(m.startswith("y0 is not determined with p2 and s2 free") for m in deg["messages"])
    assert all("--estimate f,x0,y0,k1,k2,k3" in p["message"] for p in found.values())
    # with decentering and prism held, as the line suggests, the principal point is determined and nothing is said
    held = bundle_adjust(ss.data, GRANASAT, BundleOptions(estimate=WITHOUT_PRISM), screen=False)
    assert degeneracies(held.normal, held.estimate, held.normal_u_diag)["principal_point_prism"] == []


def _shifted_truth(shift_px: float):
    """GRANASAT moved ``shift_px`` along y0's prism shift: the real fit's situation (80 px from the prism-free
    point)."""
    theta = GRANASAT.model_vector(np.float64)
    return GRANASAT.with_model_vector(theta + shift_px * prism_shift_direction(1, float(theta[0])))


def test_the_stated_principal_point_sigma_is_the_spread_of_simulated_fits():
    # The stated 1-sigma (sigma^2 S^-1, S the normal matrix with the attitudes eliminated, every camera parameter
    # free) against the spread of 30 fits to independent simulated sessions of the real set's geometry, started at
    # the truth so that each ends in the truth's minimum. With 30 fits the sample standard deviation lies within
    # [0.63, 1.37] of the true one at 99.9 % (chi-square with 29 degrees of freedom).
    true = _shifted_truth(80.0)
    errors, stated = [], []
    for seed in range(30):
        ss = synthetic_session(true, 9, (560, 630), noise_px=0.3, seed=100 + seed)
        res = bundle_adjust(ss.data, true, BundleOptions(estimate=ESTIMATE_NAMES), screen=False)
        errors.append(res.theta[1:3] - true.model_vector(np.float64)[1:3])
        stated.append(np.sqrt(np.diag(res.covariance)[1:3]))
    ratio = np.std(np.array(errors), axis=0, ddof=1) / np.mean(np.array(stated), axis=0)
    assert np.all((ratio > 0.63) & (ratio < 1.37)), ratio


def test_the_fit_from_the_nominal_can_end_in_the_mirror_and_calibrate_reports_the_other_minimum():
    # The same session from the distortion-free nominal: the fit ends at the mirrored principal point (y0 160 px,
    # ~90 of its sigmas, from the truth), whose residual RMS is the truth's to 1e-4 (noise-free, the mirror leaves
    # 0.001 px: third-order terms). calibrate then runs the fit from the mirrored point and reports where it ends:
    # within 5 sigma of the truth (5 sigma: a Gaussian tail of 6e-7).
    true = _shifted_truth(80.0)
    ss = synthetic_session(true, 9, (560, 630), noise_px=0.3, seed=100)
    out = calibrate(ss.data, GRANASAT, estimate=ESTIMATE_NAMES)
    t_true = true.model_vector(np.float64)
    sigma = np.sqrt(np.diag(out.covariance))
    assert abs(out.theta[2] - (t_true[2] - 160.0)) < 5 * sigma[2]
    found = {p["parameter"]: p for p in out.degeneracies["principal_point_prism"]}
    mirror = found["y0"]["mirror"]
    assert mirror["converged"]
    assert np.all(np.abs(np.array(mirror["principal_point_px"]) - t_true[1:3]) < 5 * sigma[1:3])
    assert mirror["rms_px"] == pytest.approx(out.after["rms_px"], rel=1e-3)
    assert any(m.startswith("a fit started from the mirrored principal point") for m in out.degeneracies["messages"])


def test_the_mirrored_principal_point_reflects_about_the_prism_free_point():
    # Pure arithmetic of mirrored_principal_point: from 80 px along the shift it goes to -80 px, and back.
    theta = _shifted_truth(80.0).model_vector(np.float64)
    item = [{"parameter": "y0"}]
    mirrored = mirrored_principal_point(theta, item)
    expected = _shifted_truth(-80.0).model_vector(np.float64)
    assert mirrored[2] == pytest.approx(expected[2], abs=1e-9)
    assert mirrored[7] == pytest.approx(expected[7], rel=1e-9) and mirrored[9] == pytest.approx(expected[9], rel=1e-9)
    assert np.allclose(mirrored_principal_point(mirrored, item), theta, rtol=1e-12, atol=1e-12)


def test_no_second_fit_when_the_mirrored_point_is_this_one():
    # Seed 004's camera has no decentering or prism: p - s = 0 at the fit to within its noise, the mirrored start is
    # the fit itself, and calibrate says so instead of fitting again.
    ss = synthetic_session(seed004_true_camera(), 200, seed=8)
    out = calibrate(ss.data, seed004_true_camera())
    assert {p["parameter"] for p in out.degeneracies["principal_point_prism"]} == {"x0", "y0"}
    assert all("mirror" not in p for p in out.degeneracies["principal_point_prism"])
    assert any(m.startswith("the mirrored principal point is this one") for m in out.degeneracies["messages"])


def test_a_mirror_fit_that_returns_is_reported_as_no_second_minimum():
    theta = GRANASAT.model_vector(np.float64)
    sigma = np.full(10, 1.0)
    back = {"theta": theta + 0.5, "rms_px": 0.3, "n_stars": 100, "converged": True, "this_rms_px": 0.3}
    items, message = mirror_report([{"parameter": "y0"}], theta, sigma, {**back, "this_n_stars": 100})
    assert message.startswith("a fit started from the mirrored principal point returns to this one")
    assert items[0]["mirror"]["sigmas_apart"] == [0.5, 0.5]
    away = {**back, "theta": theta + np.r_[0.0, 0.0, 160.0, np.zeros(7)], "this_n_stars": 100}
    _, message = mirror_report([{"parameter": "y0"}], theta, sigma, away)
    assert "ends at (666.0, 600.0) px, 0 and 160 sigma from this one" in message
