"""The calibration's plots and report say what they show (issue 31): ``calibrate --plot`` writes the residual field
before (nominal camera) and after, and the convergence plot, whose stages (a change in the stars fitted) are found
from the history; the terminal's iteration count is the live lines' numbering; distortion values carry their units;
an attitude trade-off never reads "100 %" beside a finite sigma."""

import contextlib
import io
import json

import numpy as np
import pytest

from hostlink.api import DISTORTION_UNITS, iterations_text
from hostlink.calibration.plots import _stages
from hostlink.cli import main
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate
from onboard.params import DISTORTION_NAMES

HISTORY = [
    {"iteration": 1, "rms_px": 0.068, "step_sigmas": 58.0, "n_obs": 1439, "cost": 3.35},
    {"iteration": 2, "rms_px": 0.067, "step_sigmas": 9.0, "n_obs": 1439, "cost": 3.26},
    {"iteration": 4, "rms_px": 0.067, "step_sigmas": 9.0, "n_obs": 14593, "cost": 32.9},
    {"iteration": 5, "rms_px": 0.067, "step_sigmas": 0.29, "n_obs": 14593, "cost": 32.9},
]


def test_stages_begin_where_the_number_of_stars_changes():
    assert _stages(HISTORY) == [(0, 1, "1439 stars"), (2, 3, "14593 stars")]
    named = [{"iteration": k + 1, "cost": 1.0, "stage": s} for k, s in enumerate(["f", "f", "all", "all", "all"])]
    assert _stages(named) == [(0, 1, "f"), (2, 4, "all")]


def test_the_iteration_count_is_the_live_lines_numbering():
    """The live lines print each evaluated step with its iteration number (iteration 3 ended a stage unevaluated):
    the summary says 5 iterations, as the last live line, and how many were evaluated."""
    assert iterations_text(HISTORY) == "5 iterations (4 evaluated steps)"
    assert iterations_text(HISTORY[:2]) == "2 iterations"


def test_every_distortion_coefficient_has_its_unit():
    assert set(DISTORTION_UNITS) == set(DISTORTION_NAMES)
    assert DISTORTION_UNITS["k1"] == "px^-2" and DISTORTION_UNITS["k3"] == "px^-6" and DISTORTION_UNITS["p1"] == "px^-1"


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("plots")
    write_session(d / "s.csv", simulate(seed004_config(frames=300, seed=8)).session)
    argv = ["calibrate", str(d / "s.csv"), "--nominal", "builtin:seed004_nominal", "--out", str(d / "cal.json")]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main([*argv, "--plot", str(d / "plots")]) == 0
    (d / "stdout.txt").write_text(printed.getvalue())
    return d


def test_calibrate_plot_writes_before_after_and_convergence(calibrated):
    out = (calibrated / "stdout.txt").read_text()
    for name in ("residual_field.png", "residual_field_before.png", "convergence.png"):
        data = (calibrated / "plots" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000, name
        assert name in out
    for k in DISTORTION_NAMES:
        assert f"{k} [{DISTORTION_UNITS[k]}]" in out


def test_an_attitude_tradeoff_states_what_is_left_not_100_percent(calibrated):
    """The seed 004 field (10 deg) leaves the principal point almost interchangeable with attitude: the message
    gives the share absorbed to enough digits not to round to 100 %, and the share left that sets its sigma."""
    result = json.loads((calibrated / "cal.json").read_text())
    trade = {t["parameter"]: t["information_absorbed_by_attitude"] for t in result["degeneracies"]["attitude_tradeoff"]}
    messages = [m for m in result["degeneracies"]["messages"] if "trades off against attitude" in m]
    assert trade and len(messages) == len(trade)
    for m in messages:
        assert "100 %" not in m and "remaining" in m and "1-sigma" in m
    assert all(0 < v < 1 for v in trade.values()) and np.isfinite(list(trade.values())).all()
