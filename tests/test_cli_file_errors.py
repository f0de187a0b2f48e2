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
