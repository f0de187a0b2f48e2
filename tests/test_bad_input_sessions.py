"""One clear line and a non-zero exit for sessions that cannot give a result: a parameter file of another detector,
no identified star, no frame with enough stars."""

import json
from dataclasses import replace

import numpy as np
import pytest

from hostlink.cli import main
from hostlink.files.params import data_file
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate

NOMINAL = str(data_file("seed004_nominal.json"))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return simulate(seed004_config(frames=8, seed=5)).session


def _run(capsys, argv):
    code = main(argv)
    err = capsys.readouterr().err
    return code, err


@pytest.mark.parametrize("command", ["calibrate", "replay", "attitude"])
def test_a_parameter_file_of_a_smaller_detector_is_refused(tmp_path, capsys, session, command):
    small = json.loads(open(NOMINAL).read()) | {"image_size_px": [640, 480], "principal_point_px": [319.5, 239.5]}
    (tmp_path / "small.json").write_text(json.dumps(small))
    write_session(tmp_path / "s.csv", session)
    flag = "--params" if command == "attitude" else "--nominal"
    code, err = _run(
        capsys, [command, str(tmp_path / "s.csv"), flag, str(tmp_path / "small.json"), "--out", str(tmp_path / "o")]
    )
    assert code == 2 and "off the 640 x 480 px detector" in err and err.count("\n") == 1


def test_attitude_refuses_a_session_without_identified_stars(tmp_path, capsys, session):
    s = replace(session, star_id=np.zeros_like(session.star_id))
    write_session(tmp_path / "s.csv", s)
    code, err = _run(
        capsys, ["attitude", str(tmp_path / "s.csv"), "--params", NOMINAL, "--out", str(tmp_path / "a.csv")]
    )
    assert code == 2 and "every star_id is 0" in err and err.count("\n") == 1


def test_attitude_with_no_solvable_frame_exits_non_zero(tmp_path, capsys, session):
    first = np.concatenate([[True], session.frame[1:] != session.frame[:-1]])  # one star per frame
    write_session(tmp_path / "s.csv", session.select(np.flatnonzero(first)))
    code, err = _run(
        capsys, ["attitude", str(tmp_path / "s.csv"), "--params", NOMINAL, "--out", str(tmp_path / "a.csv")]
    )
    assert code == 2 and "no frame solved" in err and err.count("\n") == 1
    assert (tmp_path / "a.csv").exists()  # the per-frame statuses say why
