"""File errors a user causes with a path the command's own checks let through (a 5,000-character name, a
--spool-dir that is no folder) are one line, ``PATH: reason``, exit 2: not an internal error (exit 1)."""

from __future__ import annotations

import pytest

from hostlink.cli import main
from hostlink.files.params import data_file
from hostlink.sky.simulate import seed004_config, simulate


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from hostlink.files.session import write_session

    path = tmp_path_factory.mktemp("s") / "s.csv"
    write_session(path, simulate(seed004_config(frames=3, seed=1)).session)
    return path


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "internal error" not in err and "Traceback" not in err
    return err


def test_a_path_too_long_for_the_file_system_is_a_one_line_error(session, tmp_path, capsys):
    too_long = "9" * 5000
    code = main(["centroid", "--out", str(tmp_path / "c.csv"), str(session), "--dark", too_long])
    err = _one_line(capsys)
    assert code == 2 and "File name too long" in err and len(err) < 400
    assert not (tmp_path / "c.csv").exists()


@pytest.mark.parametrize("spool", ["missing", "a-file"])
def test_a_spool_dir_that_is_no_folder_is_a_one_line_error(session, tmp_path, capsys, spool):
    (tmp_path / "a-file").write_text("x\n")
    out = tmp_path / "c.json"
    nominal = str(data_file("seed004_nominal.json"))
    code = main(
        ["calibrate", "--nominal", nominal, "--out", str(out), str(session), "--spool-dir", str(tmp_path / spool)]
    )
    err = _one_line(capsys)
    assert code == 2 and "spool folder" in err and not out.exists()


def test_an_output_under_a_file_says_not_a_directory(session, tmp_path, capsys):
    (tmp_path / "a-file").write_text("x\n")
    out = tmp_path / "a-file" / "c.json"
    code = main(["calibrate", "--nominal", str(data_file("seed004_nominal.json")), "--out", str(out), str(session)])
    err = _one_line(capsys)
    assert code == 2 and "Not a directory" in err and (tmp_path / "a-file").read_text() == "x\n"


def test_a_parameter_file_that_cannot_be_written_prints_nothing_on_stdout(tmp_path, capsys):
    """``params --out`` and ``accept --out`` print the set and write it: a failed write leaves nothing on stdout to be
    taken for a result (the file is written first)."""
    from hostlink.errors import UserError
    from hostlink.files.params import emit_param_file

    with pytest.raises(UserError, match="cannot write"):
        emit_param_file({"focal_length_mm": 70.0}, tmp_path)  # a directory
    assert capsys.readouterr().out == ""
    emit_param_file({"focal_length_mm": 70.0}, tmp_path / "p.json")
    assert capsys.readouterr().out == (tmp_path / "p.json").read_text()
