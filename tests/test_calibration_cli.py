"""``hostlink calibrate`` end to end: result file contents, plots, and one-line errors on bad input."""

import json

import pytest

from hostlink.cli import main
from hostlink.files.params import data_file
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_camera, seed004_config, simulate

NOMINAL = str(data_file("seed004_nominal.json"))


@pytest.fixture(scope="module")
def session_path(tmp_path_factory):
    cfg = seed004_config(frames=120, seed=31)
    cfg = type(cfg)(**{**cfg.__dict__, "misid_fraction": 0.03, "false_star_fraction": 0.1})
    sim = simulate(cfg)
    path = tmp_path_factory.mktemp("cal") / "s.csv"
    write_session(path, sim.session)
    return path


def test_calibrate_writes_parameters_sigma_statistics_and_plots(session_path, tmp_path, capsys):
    out = tmp_path / "r.json"
    code = main(
        ["calibrate", str(session_path), "--nominal", NOMINAL, "--out", str(out), "--plot", str(tmp_path / "plots")]
    )
    assert code == 0
    r = json.loads(out.read_text())
    truth = seed004_camera()
    # f within 5 of its own sigma of the truth (sigma ~0.002 mm at 120 frames)
    assert abs(r["focal_length_mm"] - truth.focal_length_mm) < 5 * r["sigma"]["focal_length_mm"]
    assert r["method"] == "bundle"
    assert set(r["sigma"]["distortion"]) == {"k1", "k2", "k3", "p1", "p2", "s1", "s2"}
    assert r["residuals"]["after"]["rms_px"] < r["residuals"]["before"]["rms_px"]
    assert r["interstar_rms_rad"]["after"] < r["interstar_rms_rad"]["before"]
    assert r["n_rejected"]["total_stars"] > 0  # the simulated 3 % misidentified stars
    assert r["references"]["unidentified_rows"] > 0  # the false stars (star_id 0) are not used
    assert any("x0" in m for m in r["degeneracies"]["messages"])
    assert (tmp_path / "plots" / "residual_field.png").stat().st_size > 1000
    assert (tmp_path / "plots" / "convergence.png").stat().st_size > 1000
    assert "interstar RMS" in capsys.readouterr().out


@pytest.mark.parametrize("method", ["cosine", "seed004"])
def test_seed_methods_are_selectable(session_path, tmp_path, method):
    out = tmp_path / "r.json"
    assert (
        main(["calibrate", str(session_path), "--nominal", NOMINAL, "--out", str(out), "--method", method, "--quiet"])
        == 0
    )
    r = json.loads(out.read_text())
    assert r["method"] == method
    assert r["sigma"]["fixed"]  # these methods leave some parameters at their nominal values


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--estimate", "f,bogus"], "unknown parameter 'bogus'"),
        (["--noise-px", "-1"], "--noise-px"),
        (["--weather", "10,1013"], "--weather needs --site"),
    ],
)
def test_bad_options_are_one_line_errors(session_path, tmp_path, capsys, extra, needle):
    code = main(["calibrate", str(session_path), "--nominal", NOMINAL, "--out", str(tmp_path / "r.json"), *extra])
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert len(err.splitlines()) == 1 and needle in err


def test_missing_session_is_one_line_error(tmp_path, capsys):
    code = main(["calibrate", str(tmp_path / "none.csv"), "--nominal", NOMINAL, "--out", str(tmp_path / "r.json")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "no such file" in err


def test_reference_directions_come_from_hipparcos_when_the_file_has_none(session_path, tmp_path):
    from hostlink.files.session import read_session

    s = read_session(session_path)
    s.ra_deg = None
    s.dec_deg = None
    bare = tmp_path / "bare.csv"
    write_session(bare, s)
    with_radec, without = tmp_path / "a.json", tmp_path / "b.json"
    assert main(["calibrate", str(session_path), "--nominal", NOMINAL, "--out", str(with_radec), "--quiet"]) == 0
    assert main(["calibrate", str(bare), "--nominal", NOMINAL, "--out", str(without), "--quiet"]) == 0
    a, b = json.loads(with_radec.read_text()), json.loads(without.read_text())
    assert b["references"]["source"] == "hipparcos"
    # the file's ra/dec are written to 1e-10 deg (0.4 mas): the two calibrations agree far inside their sigma
    assert abs(a["focal_length_mm"] - b["focal_length_mm"]) < 0.01 * a["sigma"]["focal_length_mm"]
