"""``--json`` on the batch commands (issue 31): one JSON object on stdout, nothing else there, with the same keys
(and values) as the file the command writes: calibrate and replay their parameter file, identify its report,
attitude one object per row of ATTITUDE.csv."""

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from hostlink.cli import main
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate

NOMINAL = "builtin:seed004_nominal"


@pytest.fixture(scope="module")
def session_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("json") / "s.csv"
    write_session(path, simulate(seed004_config(frames=60, seed=4)).session)
    return str(path)


def stdout_object(capsys, argv, code=0):
    assert main(argv) == code
    out = capsys.readouterr().out
    return json.loads(out)  # the whole of stdout is one object


def test_calibrate_json_is_the_result_file(session_path, tmp_path, capsys):
    out = tmp_path / "cal.json"
    obj = stdout_object(capsys, ["calibrate", session_path, "--nominal", NOMINAL, "--out", str(out), "--json"])
    assert obj == json.loads(out.read_text()) and obj["status"] == "converged"


def test_calibrate_json_of_a_kept_failure_is_printed_and_the_exit_code_stays(session_path, tmp_path, capsys):
    out = tmp_path / "cal.json"
    argv = ["calibrate", session_path, "--nominal", NOMINAL, "--out", str(out), "--json", "--max-iter", "1"]
    obj = stdout_object(capsys, [*argv, "--keep-failed"], code=2)
    assert obj == json.loads(out.read_text()) and obj["status"] == "not_converged"


def test_replay_json_is_the_estimate_file(session_path, tmp_path, capsys):
    out = tmp_path / "onboard.json"
    obj = stdout_object(capsys, ["replay", session_path, "--nominal", NOMINAL, "--out", str(out), "--json"])
    assert obj == json.loads(out.read_text()) and obj["method"] == "onboard-recursive-ud"


def test_attitude_json_rows_are_the_files_rows(session_path, tmp_path, capsys):
    out = tmp_path / "att.csv"
    argv = ["attitude", session_path, "--params", "builtin:seed004_camera", "--out", str(out), "--json"]
    obj = stdout_object(capsys, argv)
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert obj["n_frames"] == len(rows) == len(obj["frames"]) == 60 and obj["n_solved"] == 60
    for record, row in zip(obj["frames"], rows, strict=True):
        assert list(record) == list(row)  # the same keys, in the file's order
        for key, text in row.items():
            value = record[key]
            if isinstance(value, float):
                assert math.isclose(value, float(text), rel_tol=0, abs_tol=0) or key == "residual_rms_arcsec"
                if key == "residual_rms_arcsec":
                    assert f"{value:.4f}" == text
            else:
                assert str(value) == text


def test_identify_json_is_the_report_file(tmp_path, capsys):
    sim = simulate(seed004_config(frames=4, seed=11))
    blind = replace(sim.session, star_id=np.zeros_like(sim.session.star_id), ra_deg=None, dec_deg=None)
    path = tmp_path / "blind.csv"
    write_session(path, blind)
    report = tmp_path / "report.json"
    argv = ["identify", str(path), "--nominal", NOMINAL, "--out", str(tmp_path / "id.csv"), "--report", str(report)]
    obj = stdout_object(capsys, [*argv, "--json"])
    assert obj == json.loads(report.read_text()) and obj["frames"]
