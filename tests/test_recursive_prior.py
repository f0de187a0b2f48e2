"""The onboard estimator restarted from a calibrated set with that set's 1-sigma as its prior (onboard.prior):
the sigma is parsed and validated as host and sensor both do, the estimator starts at (inflated) file sigma without
burn-in, stays consistent with the truth (errors drawn from the full ground covariance, the prior given only its
marginals, as on the wire), matches the information-form posterior, does not wander like a burn-in restart, and
``hostlink replay --prior file|cold`` drives it."""

import json
from dataclasses import replace

import numpy as np
import pytest
from recursive_synth import SEED004_TRUE, crb_information, make_frames

from hostlink.cli import main
from hostlink.files.params import save_params
from hostlink.files.session import write_session
from hostlink.files.trace import read_trace
from hostlink.sky.simulate import seed004_config, simulate
from onboard import recursive
from onboard.params import ESTIMATE_NAMES, ParameterError
from onboard.prior import (
    CORRELATION_INFLATION,
    prior_config,
    prior_sigma,
    sigma_from_dict,
    sigma_to_dict,
    validate_sigma,
)

NOISE_PX = 0.05
PITCH_UM = SEED004_TRUE.pixel_pitch_um


def to_param_units(model_sigma):
    out = np.array(model_sigma, dtype=np.float64)
    out[0] *= PITCH_UM / 1000.0
    return out


# ------------------------------------------------------------------------------------------------ sigma values
def test_sigma_is_read_from_the_file_layout_and_the_flat_layout():
    file_layout = {
        "focal_length_mm": 7e-4,
        "principal_point_px": [1.3, None],
        "distortion": {"k1": 1.4e-10},
        "fixed": [],
        "unobservable": ["y0"],
    }
    got = sigma_from_dict(file_layout)
    assert got[0] == 7e-4 and got[1] == 1.3 and np.isnan(got[2]) and got[3] == 1.4e-10 and np.all(np.isnan(got[4:]))
    flat = sigma_from_dict({"f": 7e-4, "x0": 1.3, "s2": 2e-8})
    assert flat[0] == 7e-4 and flat[1] == 1.3 and flat[9] == 2e-8 and np.isnan(flat[2])
    assert np.all(np.isnan(sigma_from_dict(None)))
    back = sigma_to_dict(got)
    assert back["principal_point_px"] == [1.3, None] and back["distortion"]["k2"] is None
    assert np.array_equal(sigma_from_dict(back), got, equal_nan=True)
    assert sigma_to_dict(np.zeros(10)) is None  # 0 = unknown: nothing to write


@pytest.mark.parametrize(
    ("sigma", "field"),
    [
        ({"principal_point_px": [-1.0, 1.0]}, "sigma.principal_point_px[0]"),
        ({"focal_length_mm": float("inf")}, "sigma.focal_length_mm"),
        ({"distortion": {"s2": -1e-8}}, "sigma.distortion.s2"),
        ({"focal_length_mm": "small"}, "sigma.focal_length_mm"),
    ],
    ids=["negative", "infinite", "negative-distortion", "not-a-number"],
)
def test_a_bad_sigma_is_refused_with_its_field(sigma, field):
    with pytest.raises(ParameterError) as exc:
        sigma_from_dict(sigma)
    assert exc.value.field == field


def test_nan_and_zero_are_unknown_and_fall_back_to_the_cold_start_prior():
    validate_sigma(np.array([np.nan, 0.0] + [1e-9] * 8))  # accepted
    cold = recursive.default_prior_sigma(SEED004_TRUE)
    sigma = np.full(10, np.nan)
    sigma[1] = 0.0
    sigma[2] = 1.3
    got = prior_sigma(SEED004_TRUE, sigma)
    assert got[2] == CORRELATION_INFLATION * 1.3
    assert np.array_equal(np.delete(got, 2), np.delete(cold, 2))


def test_burn_in_is_kept_unless_every_estimated_parameter_has_a_refined_prior():
    base = recursive.RecursiveConfig()
    sigma = np.full(10, np.nan)
    sigma[:3] = (7e-4, 1.3, 1.3)
    mixed = prior_config(base, SEED004_TRUE, sigma)  # distortion starts cold: the state is still far off there
    assert mixed.burn_in_frames == base.burn_in_frames and mixed.drift_start_frames == base.drift_start_frames
    refined = prior_config(base, SEED004_TRUE, sigma, ("f", "x0", "y0"))
    assert refined.burn_in_frames == 0 and refined.drift_start_frames == base.drift_window_frames
    assert prior_config(base, SEED004_TRUE, None) == base  # nothing known: a cold start, unchanged


def test_the_estimator_starts_at_the_inflated_file_sigma():
    sigma = to_param_units(np.linspace(0.1, 1.0, 10) * recursive.default_prior_sigma(SEED004_TRUE) / 10)
    state = recursive.create(SEED004_TRUE, ESTIMATE_NAMES, prior_config(None, SEED004_TRUE, sigma), np.float32)
    got = np.array([recursive.sigma(state)[n] for n in ESTIMATE_NAMES])
    # float32 storage of the scale: relative rounding 2^-24, times a few operations
    np.testing.assert_allclose(got, CORRELATION_INFLATION * sigma, rtol=1e-6)


# ---------------------------------------------------------------------------------------- refinement runs
N_SEEDS = 8
N_FRAMES = 200
CHECKPOINTS = (1, 25, 100, 200)


@pytest.fixture(scope="module")
def refinement_runs():
    """Per seed: a ground calibration's error drawn from its full covariance (the interstar CRB of 100 frames), the
    prior given only its marginal sigmas; then 200 onboard frames from that set, with the prior (no burn-in) and,
    for comparison, the same prior with the cold-start burn-in."""
    truth = SEED004_TRUE
    idx = np.arange(10)
    p_ground = np.linalg.inv(crb_information(truth, make_frames(truth, 100, NOISE_PX, seed=100), NOISE_PX, idx))
    marginal = to_param_units(np.sqrt(np.diag(p_ground)))
    chol = np.linalg.cholesky(p_ground)
    theta_t = truth.model_vector()
    runs = []
    for seed in range(N_SEEDS):
        rng = np.random.default_rng(seed)
        cal = truth.with_vector(to_param_units(theta_t + chol @ rng.normal(size=10)))
        frames = make_frames(truth, N_FRAMES, NOISE_PX, seed=1000 + seed)
        refined = prior_config(None, cal, marginal)
        out = {}
        for label, cfg in (("file", refined), ("file+burn-in", replace(refined, burn_in_frames=300))):
            st = recursive.create(cal, ESTIMATE_NAMES, cfg, np.float32)
            rows = {}
            for k, fr in enumerate(frames, 1):
                recursive.update(st, fr.x_px, fr.y_px, fr.r, fr.identified)
                if k in CHECKPOINTS:
                    rows[k] = (recursive.state_vector(st) - theta_t, np.sqrt(np.diag(recursive.covariance(st))))
            out[label] = rows
        prior_model = np.array(refined.prior_sigma)
        prior_model[0] *= 1000.0 / PITCH_UM
        info_o = crb_information(truth, frames, NOISE_PX, idx)
        out["posterior_sigma"] = np.sqrt(np.diag(np.linalg.inv(np.diag(prior_model**-2) + info_o)))
        runs.append(out)
    return runs


def _rms_z(runs, label, k):
    z = np.array([r[label][k][0][:3] / r[label][k][1][:3] for r in runs])
    return np.sqrt(np.mean(z**2, axis=0))


@pytest.mark.slow  # Monte Carlo over seeds (issue 29: the fast lane is pytest -m 'not slow')
def test_a_refinement_stays_consistent_with_its_own_sigma(refinement_runs):
    for k in CHECKPOINTS:
        # normalised error of f, x0, y0 over 8 seeds: RMS of a unit normal sample of 8 exceeds 1.6 with p ~ 3 %;
        # without the correlation inflation it reached 1.7-2.2 (onboard.prior docstring)
        assert np.all(_rms_z(refinement_runs, "file", k) < 1.6), (k, _rms_z(refinement_runs, "file", k))


@pytest.mark.slow  # Monte Carlo over seeds (issue 29: the fast lane is pytest -m 'not slow')
def test_the_filter_sigma_matches_the_information_form_posterior(refinement_runs):
    # Kalman filter without burn-in = prior information + data information (the Cramer-Rao bound of the prior and the
    # 200 frames). 15 %: the filter linearises at its estimate, up to ~10 px off along the weak principal point /
    # decentering / prism direction, where the Jacobian column itself changes to first order (onboard.recursive
    # docstring); measured up to 11 % (x0, p1, s1) over these 8 seeds
    for r in refinement_runs:
        np.testing.assert_allclose(r["file"][N_FRAMES][1], r["posterior_sigma"], rtol=0.15)


@pytest.mark.slow  # Monte Carlo over seeds (issue 29: the fast lane is pytest -m 'not slow')
def test_a_refined_prior_does_not_wander_like_a_burn_in_restart(refinement_runs):
    def rms_err(label, k):
        return np.sqrt(np.mean([r[label][k][0][1:3] ** 2 for r in refinement_runs]))

    start = rms_err("file", 1)
    # the burn-in erases the prior (x k in sigma) and the principal point wanders off; without it the error never
    # grows past its starting value by more than the sample scatter (20 %)
    assert rms_err("file+burn-in", 25) > 1.5 * start
    assert max(rms_err("file", k) for k in CHECKPOINTS) < 1.2 * start
    assert rms_err("file", N_FRAMES) <= rms_err("file+burn-in", N_FRAMES) * 1.1  # and ends no worse


# ----------------------------------------------------------------------------------------------- the CLI
@pytest.fixture(scope="module")
def calibrated_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prior")
    sim = simulate(seed004_config(150, seed=4))
    write_session(tmp / "session.csv", sim.session)
    truth = sim.truth["camera"]
    sigma = {
        "focal_length_mm": 7e-4,
        "principal_point_px": [1.3, 1.3],
        "distortion": {"k1": 1.4e-10, "k2": 5.8e-16, "k3": 7.4e-22, "p1": 2.2e-8, "p2": 2.1e-8, "s1": 2e-8, "s2": 2e-8},
        "fixed": [],
        "unobservable": [],
    }
    calibrated = dict(
        truth,
        principal_point_px=[truth["principal_point_px"][0] + 1.0, truth["principal_point_px"][1] - 1.0],
        sigma=sigma,
    )
    (tmp / "calibrated.json").write_text(json.dumps(calibrated))
    save_params(tmp / "plain.json", SEED004_TRUE)
    return tmp


def _trace_first_row(path):
    return {name: values[0] for name, values in read_trace(path).items()}


def test_replay_starts_from_the_file_sigma_by_default_and_from_cold_on_request(calibrated_files, capsys):
    tmp = calibrated_files
    common = [str(tmp / "session.csv"), "--nominal", str(tmp / "calibrated.json")]
    assert main(["replay", *common, "--out", str(tmp / "file.json"), "--trace", str(tmp / "file.csv")]) == 0
    assert (
        main(["replay", *common, "--out", str(tmp / "cold.json"), "--trace", str(tmp / "cold.csv"), "--prior", "cold"])
        == 0
    )
    file_doc, cold_doc = (json.loads((tmp / n).read_text()) for n in ("file.json", "cold.json"))
    assert (file_doc["prior"], file_doc["burn_in_frames"]) == ("file", 0)
    assert (cold_doc["prior"], cold_doc["burn_in_frames"]) == ("cold", 300)
    # after one frame the x0 sigma is at most the prior's (2 x 1.3 px), far below the cold start's 51 px
    assert float(_trace_first_row(tmp / "file.csv")["sigma_x0_px"]) <= CORRELATION_INFLATION * 1.3
    assert float(_trace_first_row(tmp / "cold.csv")["sigma_x0_px"]) > 10.0
    truth = simulate(seed004_config(1, seed=4)).truth["camera"]["principal_point_px"]
    for doc in (file_doc, cold_doc):  # both converge near the truth (cold: from 1 px off with the wide prior)
        err = np.subtract(doc["principal_point_px"], truth)
        sig = list(sigma_from_dict(doc["sigma"])[1:3])
        assert np.all(np.abs(err) < 4 * np.array(sig)), (doc["prior"], err, sig)  # 4 sigma: a 1-in-16000 event
    capsys.readouterr()


def test_replay_refuses_a_missing_or_bad_sigma_on_one_line(calibrated_files, capsys):
    tmp = calibrated_files
    code = main(
        [
            "replay",
            str(tmp / "session.csv"),
            "--nominal",
            str(tmp / "plain.json"),
            "--out",
            str(tmp / "x.json"),
            "--prior",
            "file",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "sigma" in err
    bad = json.loads((tmp / "calibrated.json").read_text())
    bad["sigma"]["principal_point_px"] = [-1.0, 1.0]
    (tmp / "bad.json").write_text(json.dumps(bad))
    code = main(["replay", str(tmp / "session.csv"), "--nominal", str(tmp / "bad.json"), "--out", str(tmp / "x.json")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "sigma.principal_point_px[0]" in err
