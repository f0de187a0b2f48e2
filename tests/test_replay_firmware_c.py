"""``hostlink replay --firmware c``: the C firmware core (onboard/c) runs the onboard estimator over a session
through the same command, and its estimate and trace agree with the Python sensor's (float32 and fixed)."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
from test_replay_cli import NOMINAL

from hostlink.cli import main
from hostlink.errors import UserError
from hostlink.files.params import load_params
from hostlink.files.session import write_session
from hostlink.portkit import estimator_c, firmware_c
from hostlink.sky.simulate import seed004_config, simulate

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")


@pytest.fixture(scope="module")
def session_files(tmp_path_factory):
    directory = tmp_path_factory.mktemp("replay_c")
    write_session(directory / "session.csv", simulate(seed004_config(400, seed=7)).session)
    (directory / "nominal.json").write_text(json.dumps(NOMINAL))
    return directory


def _replay(directory, precision: str, firmware: str):
    out = directory / f"estimate_{precision}_{firmware}.json"
    trace = directory / f"trace_{precision}_{firmware}.csv"
    args = ["replay", str(directory / "session.csv"), "--nominal", str(directory / "nominal.json"), "--out", str(out)]
    code = main([*args, "--trace", str(trace), "--precision", precision, "--firmware", firmware])
    assert code == 0
    with trace.open() as f:
        rows = list(csv.DictReader(f))
    return load_params(out), json.loads(out.read_text()), rows


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_replay_with_the_c_core_matches_the_python_sensor(session_files, precision):
    p_c, doc_c, trace_c = _replay(session_files, precision, "c")
    p_py, doc_py, trace_py = _replay(session_files, precision, "python")
    # the C core evaluates the float32 filter in the reference model's order (onboard.linalg32): the same state
    # after every frame, hence the same estimate file and trace, byte for byte
    for name in (f"estimate_{precision}_{{}}.json", f"trace_{precision}_{{}}.csv"):
        assert (session_files / name.format("c")).read_bytes() == (session_files / name.format("python")).read_bytes()
    assert np.array_equal(p_c.vector(), p_py.vector())
    assert doc_c == doc_py and trace_c == trace_py
    assert len(trace_c) == 400 and doc_c["frames_used"] > 300  # a session that updates the filter


def test_replay_firmware_c_refuses_float64_in_one_line(session_files, capsys):
    args = ["replay", str(session_files / "session.csv"), "--nominal", str(session_files / "nominal.json")]
    code = main([*args, "--out", str(session_files / "x.json"), "--precision", "float64", "--firmware", "c"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--firmware c" in err


def test_no_compiler_is_a_one_line_error(monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-27")
    with pytest.raises(UserError, match="no C compiler found") as exc:
        firmware_c.find_compiler()  # what replay --firmware c builds with
    assert "\n" not in str(exc.value)


def test_replay_firmware_c_refuses_more_stars_than_its_buffers_in_one_line(session_files, capsys):
    args = ["replay", str(session_files / "session.csv"), "--nominal", str(session_files / "nominal.json")]
    code = main([*args, "--out", str(session_files / "y.json"), "--max-stars", "40", "--firmware", "c"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "INTERSTAR_MAX_STARS = 32" in err


def test_the_binding_sizes_are_the_headers(session_files):
    text = (estimator_c.c_dir() / "interstar.h").read_text()
    assert f"#define INTERSTAR_MAX_STARS {estimator_c.MAX_STARS}" in text
    text = (estimator_c.c_dir() / "recursive.h").read_text()
    assert f"#define RECURSIVE_MAX_DRIFT_WINDOW {estimator_c.MAX_DRIFT_WINDOW}" in text
