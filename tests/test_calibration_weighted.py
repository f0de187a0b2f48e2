"""Stars weighted by their own centroid noise (the session's optional sigma_px column): the bundle whitens each star
by it, reaches the Cramer-Rao bound of a session of mixed magnitudes where the unweighted fit does not, and reports
the noise it finds relative to the given one."""

import json

import numpy as np
import pytest
from synthetic_sessions import synthetic_session

from hostlink.calibration.bundle import bundle_adjust
from hostlink.calibration.data import SPOOL_FIELDS, build_data, load_chunk, save_chunk
from hostlink.calibration.model import parameter_columns
from hostlink.calibration.normal import accumulate_normals, reduced_normal
from hostlink.calibration.run import calibrate
from hostlink.cli import main
from hostlink.files.params import data_file, load_params
from hostlink.files.session import read_session, write_session
from hostlink.sky.simulate import seed004_config, simulate
from onboard.params import ESTIMATE_NAMES

SEED004 = load_params("builtin:seed004_camera")
SEED004_NOMINAL = load_params("builtin:seed004_nominal")
ALL = parameter_columns(ESTIMATE_NAMES)
#: mixed magnitudes: each star's centroid noise log-uniform over a factor 25 (a bright star's 0.02 px to a faint
#: one's 0.5 px), as a session of stars over ~3.5 magnitudes gives it
SIGMA_RANGE_PX = (0.02, 0.5)


def mixed_session(seed: int, frames: int):
    """A session of seed 004's camera whose stars have the noise of mixed magnitudes: (data with sigma_px, the same
    data without it, the noise-free data, the true attitudes)."""
    ss = synthetic_session(SEED004, frames, noise_px=0.0, seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    n = ss.data.n_obs
    sigma = np.exp(rng.uniform(*np.log(SIGMA_RANGE_PX), n))
    x = ss.x_true_px + sigma * rng.standard_normal(n)
    y = ss.y_true_px + sigma * rng.standard_normal(n)
    frame = ss.data.frame_index()
    weighted = build_data(x, y, ss.data.r, frame, sigma_px=sigma)
    plain = build_data(x, y, ss.data.r, frame)
    return weighted, plain, build_data(ss.x_true_px, ss.y_true_px, ss.data.r, frame, sigma_px=sigma), ss


def fisher_heteroscedastic(noise_free, attitudes_true) -> np.ndarray:
    """The camera's Fisher information with each star's own noise: the Schur complement over the attitudes of
    sum J^T J / sigma_k^2 (``crb_bounds.fisher_information``'s formula with per-star weights)."""
    w = 1.0 / noise_free.sigma_px**2
    blocks = accumulate_normals(noise_free, SEED004.model_vector(), attitudes_true, ALL, w, np.ones(ALL.size))
    return reduced_normal(blocks, 0.0)[0]


def test_weighted_fit_reaches_the_bound_of_mixed_magnitudes_where_the_unweighted_one_misses_it():
    """16 sessions of 500 frames. Efficiency as the RMS error in the Fisher metric over the bound's:
    sqrt(mean NEES / K) (1 for an efficient estimator; NEES = err^T I err, chi-square(10) each, so the mean of 16
    has a standard deviation of 1.1 around 10: the ratio is 1 +- 0.035, and 1.1 is almost three of those). The
    weighted fit is within 1.1x of the bound (1.00x measured); the unweighted one (the same stars, one noise for
    all) is not (2.5x). 500 frames rather than fewer: at 100 frames the finite-sample excess of the fit itself is
    ~15 %, with equal noise too (docs/calibration.md)."""
    nees_w, nees_u = [], []
    for seed in range(16):
        weighted, plain, noise_free, ss = mixed_session(seed, 500)
        info = fisher_heteroscedastic(noise_free, ss.attitudes_true)
        for data, out in ((weighted, nees_w), (plain, nees_u)):
            err = (bundle_adjust(data, SEED004_NOMINAL).theta - SEED004.model_vector())[ALL]
            out.append(float(err @ info @ err))
    ratio_w = np.sqrt(np.mean(nees_w) / ALL.size)
    ratio_u = np.sqrt(np.mean(nees_u) / ALL.size)
    assert ratio_w <= 1.1, f"weighted {ratio_w:.3f}x the bound"
    assert ratio_u > 1.1, f"unweighted {ratio_u:.3f}x the bound"


def test_fitted_noise_scale_is_the_noise_relative_to_the_given_sigma():
    """The weights are relative: sigma_px given twice too small weighs the stars alike and the fit reports a noise
    scale of ~2 instead of ~1 (within 5 %: sqrt(2 / dof) ~ 1.5 % here), its covariance scaled by its square. The
    same camera within 0.01 sigma, not to the bit: the robust scale comes from a histogram of log-spaced bins 0.25 %
    wide, so the Huber threshold moves by a fraction of a bin, and each fit stops within remainder_tol = 0.005 sigma
    of its minimum; the scale and the covariance to 1e-3 for the same reason."""
    weighted, _, _, _ = mixed_session(3, 150)
    right = calibrate(weighted, SEED004_NOMINAL)
    halved = build_data(
        weighted.x_px, weighted.y_px, weighted.r, weighted.frame_index(), sigma_px=weighted.sigma_px / 2
    )
    low = calibrate(halved, SEED004_NOMINAL)
    assert right.noise_scale == pytest.approx(1.0, abs=0.05)
    assert low.noise_scale == pytest.approx(2.0 * right.noise_scale, rel=1e-3)
    cols = [ESTIMATE_NAMES.index(n) for n in right.estimate]
    sigma = np.sqrt(np.diag(right.covariance))
    assert low.estimate == right.estimate
    assert np.all(np.abs(low.theta - right.theta)[cols] < 0.01 * sigma)
    np.testing.assert_allclose(np.diag(low.covariance), np.diag(right.covariance), rtol=1e-3)


def test_spooled_chunk_keeps_the_stars_noise(tmp_path):
    weighted, plain, _, _ = mixed_session(1, 20)
    for data in (weighted, plain):
        save_chunk(tmp_path / "c.spool", data)
        back = load_chunk(tmp_path / "c.spool")
        if data.sigma_px is None:
            assert back.sigma_px is None
        else:
            np.testing.assert_array_equal(back.sigma_px, data.sigma_px)


def test_a_chunk_spooled_without_the_noise_record_reads_as_one_without_noise(tmp_path):
    """Chunks spooled before the sigma_px record existed end after ``row``: they read back whole, without noise."""
    _, plain, _, _ = mixed_session(2, 10)
    with open(tmp_path / "old.spool", "wb") as f:
        for name in SPOOL_FIELDS[:-1]:
            np.save(f, np.ascontiguousarray(plain.source_rows() if name == "row" else getattr(plain, name)))
    back = load_chunk(tmp_path / "old.spool")
    assert back.sigma_px is None and back.n_obs == plain.n_obs
    np.testing.assert_array_equal(back.x_px, plain.x_px)


@pytest.fixture(scope="module")
def session_with_sigma(tmp_path_factory):
    """A simulated session written with a sigma_px column (the simulator's 0.05 px noise)."""
    session = simulate(seed004_config(frames=60, seed=5)).session
    session.extra["sigma_px"] = np.array(["0.05"] * len(session), dtype=object)
    path = tmp_path_factory.mktemp("weighted") / "s.csv"
    write_session(path, session)
    return path


def test_cli_weights_by_the_sigma_px_column_and_reports_the_noise_scale(session_with_sigma, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "calibrate",
                str(session_with_sigma),
                "--nominal",
                str(data_file("seed004_nominal.json")),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert "x the session's sigma_px" in capsys.readouterr().out
    result = json.loads(out.read_text())
    # the simulator's noise is the 0.05 px given: a scale near 1 (the simulated centroids' own noise model aside)
    assert 0.8 < result["noise_scale"] < 1.25 and result["noise_px"] is None


@pytest.mark.parametrize("model", ["auto", "constant"])
def test_cli_reports_the_noise_model_it_used(session_with_sigma, tmp_path, capsys, model):
    """The noise line names the model the result file records (auto: the data's choice, with its likelihood ratio,
    `noise_model_text`), or the floor held constant with its value when --noise-model constant tried no other."""
    from hostlink.api import noise_model_text

    out = tmp_path / "r.json"
    nominal = str(data_file("seed004_nominal.json"))
    argv = ["calibrate", str(session_with_sigma), "--nominal", nominal, "--out", str(out), "--noise-model", model]
    assert main(argv) == 0
    printed = " ".join(capsys.readouterr().out.split())  # the report wraps its lines
    result = json.loads(out.read_text())
    if model == "auto":
        assert " ".join(noise_model_text(result["noise_model"]).split()) in printed
    else:
        assert result["noise_model"]["model"] == "constant" and "to choose the radial one" not in printed
        assert f"a floor of {result['noise_floor_px'] or 0.0:.4f} px in quadrature" in printed
        assert "noise floor held constant over the field (--noise-model constant)" in printed


@pytest.mark.parametrize("value", ["-0.1", "0", "abc", ""])
def test_a_bad_sigma_px_is_a_one_line_error_naming_its_line(session_with_sigma, tmp_path, capsys, value):
    session = read_session(session_with_sigma)
    row = int(np.flatnonzero(session.star_id != 0)[5])
    session.extra["sigma_px"] = session.extra["sigma_px"].copy()
    session.extra["sigma_px"][row] = value
    path = tmp_path / "bad.csv"
    write_session(path, session)
    out = tmp_path / "r.json"
    code = main(["calibrate", str(path), "--nominal", str(data_file("seed004_nominal.json")), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and f"sigma_px on line {row + 2}" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_noise_model_choices_are_the_library_s():
    """calibrate's --noise-model lists its choices literally (the parser is built for every command, and
    hostlink.calibration.floorfit imports numpy and the calibration), so they are held here to NOISE_MODELS, the
    library's list, which refuses any other."""
    from hostlink.api import NOISE_MODELS
    from hostlink.cli import build_parser

    parser = build_parser()
    base = ["calibrate", "s.csv", "--nominal", "n.json", "--out", "r.json"]
    assert parser.parse_args(base).noise_model == NOISE_MODELS[0]
    sub = next(a for a in parser._subparsers._group_actions if a.choices).choices["calibrate"]
    (action,) = (a for a in sub._actions if a.dest == "noise_model")
    assert tuple(action.choices) == NOISE_MODELS
