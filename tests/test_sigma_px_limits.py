"""The session's ``sigma_px`` column (each star's 1-sigma centroid noise per axis) at its limits, through the CLI:
zero, negative, NaN, infinite, unparsable or beyond any detector is refused in one line naming the file line and the
column (exit 2, no result written); a positive value below the photon-noise floor of a single exposure is taken as
the floor, so that one absurdly small value (1e-9 px: a weight 10^16 times the others') no longer overflows the
weighted fit."""

import json
import math

import numpy as np
import pytest

from hostlink.calibration.data import SIGMA_PX_CEILING, SIGMA_PX_FLOOR
from hostlink.cli import main
from hostlink.files.params import data_file
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate

NOMINAL = str(data_file("seed004_nominal.json"))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A simulated session with a sigma_px column of the simulator's 0.05 px noise; the row of an identified star."""
    s = simulate(seed004_config(frames=60, seed=5)).session
    s.extra["sigma_px"] = np.array(["0.05"] * len(s), dtype=object)
    return s, int(np.flatnonzero(s.star_id != 0)[7])


def _with_value(session, tmp_path, value: str, name: str = "s.csv"):
    s, row = session
    sigma = s.extra["sigma_px"].copy()
    sigma[row] = value
    s.extra = {**s.extra, "sigma_px": sigma}
    path = tmp_path / name
    write_session(path, s)
    s.extra = {**s.extra, "sigma_px": np.array(["0.05"] * len(s), dtype=object)}
    return path, row


def _calibrate(path, out, capsys) -> tuple[int, str, str]:
    code = main(["calibrate", str(path), "--nominal", NOMINAL, "--out", str(out)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("value", ["0", "-0", "-1e-9", "nan", "inf", "-inf", "1e999", "1e300", "17000000", "x"])
def test_a_sigma_px_outside_its_range_is_a_one_line_refusal(session, tmp_path, capsys, value):
    path, row = _with_value(session, tmp_path, value)
    out = tmp_path / "r.json"
    code, _, err = _calibrate(path, out, capsys)
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and f"sigma_px on line {row + 2}" in err and "Traceback" not in err
    assert not out.exists()


def test_the_floor_is_the_photon_noise_bound_of_a_star_at_full_well():
    """Cramer-Rao bound of a Gaussian PSF of width s with N photo-electrons, s / sqrt(N), for the brightest
    unsaturated star (its central pixel, the pixel-integrated Gaussian's share of N, at a full well of 10^6 e-): the
    same for every width, 1 / sqrt(2 pi W), to within 1 % from s = 3 px on (the peak pixel's share tends to
    1 / (2 pi s^2) as s grows)."""
    full_well_e = 1.0e6
    for s in (3.0, 4.0, 5.0):
        peak_fraction = math.erf(0.5 / (s * math.sqrt(2.0))) ** 2  # the central pixel's share of the star's light
        n_e = full_well_e / peak_fraction
        assert s / math.sqrt(n_e) == pytest.approx(SIGMA_PX_FLOOR, rel=0.01)
    assert SIGMA_PX_CEILING == 2**24


def test_an_absurdly_small_sigma_px_is_taken_as_the_floor(session, tmp_path, capsys):
    """One star at 1e-9 px among 0.05 px ones (before: overflow warnings, LAPACK's messages on stderr and "SVD did
    not converge"): the fit runs, exit 0, nothing on stderr, and its result is the fit with that star at the floor."""
    tiny, _ = _with_value(session, tmp_path, "1e-9", "tiny.csv")
    floor, _ = _with_value(session, tmp_path, repr(SIGMA_PX_FLOOR), "floor.csv")
    code, out_text, err = _calibrate(tiny, tmp_path / "tiny.json", capsys)
    assert code == 0 and err == "", err
    assert "x the session's sigma_px" in out_text
    assert _calibrate(floor, tmp_path / "floor.json", capsys)[0] == 0
    a = json.loads((tmp_path / "tiny.json").read_text())
    b = json.loads((tmp_path / "floor.json").read_text())
    assert a["focal_length_mm"] == b["focal_length_mm"] and a["distortion"] == b["distortion"]
    assert math.isfinite(a["focal_length_mm"]) and a["noise_scale"] == b["noise_scale"]


def test_a_denormal_sigma_px_in_every_row_calibrates_at_the_floor(session, tmp_path, capsys):
    """Every star at 5e-324 px (the smallest float): all at the floor, one noise for all (the fitted scale absorbs
    it): the same camera as the column at 0.05 px, and a noise scale 0.05 / floor times larger."""
    s, _ = session
    path = tmp_path / "denormal.csv"
    s.extra = {**s.extra, "sigma_px": np.array(["5e-324"] * len(s), dtype=object)}
    write_session(path, s)
    s.extra = {**s.extra, "sigma_px": np.array(["0.05"] * len(s), dtype=object)}
    base = tmp_path / "base.csv"
    write_session(base, s)
    assert _calibrate(path, tmp_path / "d.json", capsys)[0] == 0
    assert _calibrate(base, tmp_path / "b.json", capsys)[0] == 0
    d = json.loads((tmp_path / "d.json").read_text())
    b = json.loads((tmp_path / "b.json").read_text())
    # the same fit up to where the optimiser stops (its tolerances act on the cost, which the scale multiplies):
    # within 1e-3 of the focal length's own standard error, far below anything the data can tell apart
    assert abs(d["focal_length_mm"] - b["focal_length_mm"]) < 1e-3 * b["sigma"]["focal_length_mm"]
    assert d["noise_scale"] == pytest.approx(b["noise_scale"] * 0.05 / SIGMA_PX_FLOOR, rel=1e-3)


def test_parquet_sessions_are_held_to_the_same_limits(session, tmp_path, capsys):
    pytest.importorskip("pyarrow")
    path, row = _with_value(session, tmp_path, "nan", "bad.parquet")
    code, _, err = _calibrate(path, tmp_path / "r.json", capsys)
    assert code == 2 and "sigma_px on line" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.json").exists()
