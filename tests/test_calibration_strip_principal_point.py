"""The principal point of an off-centre strip camera (docs/calibration.md, "Off-centre strip: the principal point's
stated 1-sigma"): with decentering and prism free the stated 1-sigma is that of the local minimum and lies below the
Cramer-Rao bound at the truth (the degeneracy line says so in every session); with the thin prism held it is the
spread of the fits and the bound, without bias. The onboard filter started from those fits: the same two cases."""

from __future__ import annotations

import numpy as np

from hostlink.calibration.crb import fisher_information, interstar_information
from hostlink.calibration.report import principal_point_prism_note
from hostlink.calibration.run import calibrate
from hostlink.calibration.synthetic import make_frames, synthetic_session
from onboard import recursive
from onboard.params import ESTIMATE_NAMES, params_from_dict
from onboard.prior import prior_config

#: The bench's strip camera of docs/camera-model.md: 2048 x 512 px, 16 mm, 5.5 um, principal point far off centre.
STRIP = params_from_dict(
    {
        "focal_length_mm": 16.0,
        "pixel_pitch_um": 5.5,
        "principal_point_px": [1300.0, 200.0],
        "image_size_px": [2048, 512],
        "distortion": {"k1": -5e-9, "p1": 2e-7},
    }
)
#: What a user starts from: the design focal length, the principal point at the detector centre, no distortion.
NOMINAL = params_from_dict(
    {
        "focal_length_mm": 16.0,
        "pixel_pitch_um": 5.5,
        "principal_point_px": [1023.5, 255.5],
        "image_size_px": [2048, 512],
    }
)
NOISE_PX = 0.05
N_FRAMES = 80
N_SEEDS = 40
#: Thin prism held (the strip's truth has none): the principal point is then determined at first order.
WITHOUT_PRISM = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")


def _fits(estimate):
    """(errors, stated 1-sigma, Cramer-Rao 1-sigma at the truth, outcomes) of f, x0, y0 (model units, F in px) over
    N_SEEDS sessions fitted from NOMINAL."""
    truth = STRIP.model_vector(np.float64)
    errors, stated, bound, outcomes = [], [], [], []
    for seed in range(N_SEEDS):
        ss = synthetic_session(STRIP, N_FRAMES, noise_px=NOISE_PX, seed=seed)
        out = calibrate(ss.data, NOMINAL, estimate=estimate, noise_px=NOISE_PX, mirror_fit=False)
        cols = np.array([ESTIMATE_NAMES.index(n) for n in out.estimate])
        info = fisher_information(ss.noise_free_data(), truth, ss.attitudes_true, cols, NOISE_PX)
        errors.append(out.theta[:3] - truth[:3])
        stated.append(np.sqrt(np.diag(out.covariance)[:3]))
        bound.append(np.sqrt(np.diag(np.linalg.inv(info))[:3]))
        outcomes.append(out)
    return np.array(errors), np.array(stated), np.array(bound), outcomes


def test_with_the_prism_held_the_stated_sigma_is_the_spread_and_the_bound():
    errors, stated, bound, outcomes = _fits(WITHOUT_PRISM)
    # x0 is correlated 0.977 with p1 here, but with s1 held the shift leaves d r^2 / (2 F^2) in x (first order): x0 is
    # determined, so no degeneracy line (it was printed in all 40 sessions before it required both coefficients free)
    assert all(o.degeneracies["principal_point_prism"] == [] for o in outcomes)
    assert all(principal_point_prism_note(o.degeneracies["principal_point_prism"]) is None for o in outcomes)
    spread = np.std(errors, axis=0, ddof=1)
    # 40 fits: the sample standard deviation lies within [0.63, 1.37] of the true one at 99.9 % (chi-square, 39
    # degrees of freedom); measured 1.11, 1.01, 1.23 (f, x0, y0)
    ratio = spread / np.mean(stated, axis=0)
    assert np.all((ratio > 0.63) & (ratio < 1.37)), ratio
    # the stated 1-sigma, linearised at the estimate, is the bound at the truth (measured within 1 %); 5 % allows for
    # the estimate's distance from the truth
    assert np.allclose(np.mean(stated, axis=0), np.mean(bound, axis=0), rtol=0.05)
    # unbiased: the mean error within 4 of its standard errors (a Gaussian tail of 6e-5 per parameter)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 4.0 * spread / np.sqrt(N_SEEDS)), np.mean(errors, axis=0)


def test_with_prism_free_the_stated_sigma_is_below_the_bound_and_the_report_says_so():
    # All ten free (the bundle's default set): the principal point is set by second-order terms only
    # (docs/calibration.md, "Principal point with decentering and prism free"). The strip's truth lies close to the
    # prism-free point (p1 = 2e-7 is F^2 p1 = 1.7 px of shift), where the curvature along the shift vanishes, so the
    # Cramer-Rao bound at the truth is large (12.9 px in x0) while each fit is linearised where the curvature is
    # larger: the stated 1-sigma (7 px) is that of its own minimum, and fits from the centred nominal end in
    # either minimum (x0 -12.4 px on average, spread 12.2 px, 2.9 stated sigmas RMS). The property the report must
    # keep: it says so, in the bench's summary too.
    errors, stated, bound, outcomes = _fits(None)
    for out in outcomes:
        assert {p["parameter"] for p in out.degeneracies["principal_point_prism"]} == {"x0", "y0"}
        note = principal_point_prism_note(out.degeneracies["principal_point_prism"])
        assert note.startswith("x0, y0 not determined with decentering and prism free")
        assert note.endswith(
            "hold them, --estimate f,x0,y0,k1,k2,k3, or the thin prism, --estimate " + ",".join(WITHOUT_PRISM) + ")"
        )
    # stated below the bound: measured 0.54 of it in x0 and y0; 0.8 leaves the margin of 40 sessions
    assert np.all(np.median(stated[:, 1:3], axis=0) < 0.8 * np.median(bound[:, 1:3], axis=0))
    # and the errors exceed the stated 1-sigma: RMS of error / sigma measured 2.9 (x0) and 1.5 (y0);
    # a correct sigma would give 1 (above 1.5 with probability < 1e-6 for 40 Gaussian ratios)
    z = errors[:, 1:3] / stated[:, 1:3]
    assert np.sqrt(np.mean(z[:, 0] ** 2)) > 1.5


ONBOARD_FRAMES = 500
ONBOARD_SESSIONS = 4


def _onboard_sigma_over_bound(estimate):
    """x0, y0 of the onboard filter (float64 reference) started from each host fit with its 1-sigma as uploaded
    (``onboard.prior.prior_config``), then fed ONBOARD_FRAMES new frames: (stated 1-sigma / bound, error / stated
    1-sigma) per session. The bound: the interstar Fisher information of those frames at the truth plus the filter's own
    diagonal prior (its information), inverted."""
    truth = STRIP.model_vector(np.float64)
    ratio, z = [], []
    for seed in range(ONBOARD_SESSIONS):
        ss = synthetic_session(STRIP, N_FRAMES, noise_px=NOISE_PX, seed=seed)
        out = calibrate(ss.data, NOMINAL, estimate=estimate, noise_px=NOISE_PX, mirror_fit=False)
        cols = np.array([ESTIMATE_NAMES.index(n) for n in out.estimate])
        sigma = np.full(10, np.nan)
        sigma[cols] = np.sqrt(np.diag(out.covariance))
        sigma[0] *= STRIP.pixel_pitch_um / 1000.0  # F px -> f mm, the set's units
        config = prior_config(None, out.params, sigma, out.estimate)
        state = recursive.create(out.params, out.estimate, config, np.float64)
        frames = make_frames(STRIP, ONBOARD_FRAMES, NOISE_PX, seed=1000 + seed)
        for fr in frames:
            recursive.update(state, fr.x_px, fr.y_px, fr.r, fr.identified)
        prior_model = np.array(config.prior_sigma, dtype=np.float64)[cols]
        prior_model[0] *= 1000.0 / STRIP.pixel_pitch_um
        info = interstar_information(STRIP, frames, NOISE_PX, cols) + np.diag(prior_model**-2.0)
        bound = np.sqrt(np.diag(np.linalg.inv(info))[1:3])
        stated = np.sqrt(np.diag(recursive.covariance(state))[1:3])
        error = recursive.current_params(state).model_vector(np.float64)[1:3] - truth[1:3]
        ratio.append(stated / bound)
        z.append(error / stated)
    return np.array(ratio), np.array(z)


def test_onboard_with_the_prism_held_the_stated_sigma_is_the_bound():
    # Measured 1.00-1.01 in x0 and y0 on the 4 sessions; 0.9-1.2 allows for the filter's stated excess over the bound
    # with a burn-in (4-12 %, onboard/recursive.py; none here: the prior is refined) and its linearisation.
    ratio, z = _onboard_sigma_over_bound(WITHOUT_PRISM)
    assert np.all((ratio > 0.9) & (ratio < 1.2)), ratio
    # each error within 4 stated sigmas (a Gaussian tail of 6e-5 each)
    assert np.all(np.abs(z) < 4.0), z


def test_onboard_with_prism_free_the_stated_sigma_falls_below_the_bound():
    # The known limitation (docs/calibration.md, "Off-centre strip: the principal point's stated 1-sigma"): the
    # filter, linearised in the host's minimum, states a 1-sigma below the bound at the truth: 0.32-0.67 of it on the
    # 4 sessions (medians 0.46 in x0, 0.62 in y0), against 1.00-1.01 with the prism held. Below 0.8 in the median:
    # asserted so that a change that fixes it (or hides it) is seen.
    ratio, _ = _onboard_sigma_over_bound(None)
    assert np.all(np.median(ratio, axis=0) < 0.8), ratio
