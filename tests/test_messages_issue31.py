"""Each message issue 31 found misleading now names the problem, in one line with a non-zero exit (a test per
message): a directory given to ``centroid`` or ``import-can``, an empty or non-BLF ``.blf``, a broken FITS file
(never astropy's advice to pass an option hostlink does not have), a truth or parameter JSON given to ``calibrate``
as a session, and every install hint names this project's distribution ``startracker-companion[extra]``."""

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

from hostlink.cli import main
from hostlink.errors import DISTRIBUTION, install_hint
from hostlink.files.params import data_file

ROOT = Path(__file__).resolve().parent.parent


def error_line(capsys, argv):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    return err


def test_centroid_on_a_directory_says_it_is_a_directory(tmp_path, capsys):
    (tmp_path / "night").mkdir()
    err = error_line(capsys, ["centroid", str(tmp_path / "night"), "--out", str(tmp_path / "s.csv")])
    assert "is a directory" in err and "night/*.fits" in err and "unknown image type" not in err


def test_import_can_on_a_directory_says_it_is_a_directory(tmp_path, capsys):
    err = error_line(capsys, ["import-can", str(tmp_path), "--out", str(tmp_path / "s.csv")])
    assert "is a directory" in err and "no such file" not in err


@pytest.mark.parametrize(
    ("content", "needle"),
    [(b"", "empty file, not a BLF log"), (b"date Mon Jan 1 00:00:00 2026\nbase hex\n" * 4, "not a BLF log")],
    ids=["empty", "text"],
)
def test_import_can_on_an_empty_or_non_blf_file_names_the_blf_signature(tmp_path, capsys, content, needle):
    path = tmp_path / "capture.blf"
    path.write_bytes(content)
    err = error_line(capsys, ["import-can", str(path), "--out", str(tmp_path / "s.csv")])
    assert needle in err and "LOGG" in err and "unpack" not in err and "buffer" not in err


def _fits_bytes():
    import io

    from astropy.io import fits

    buffer = io.BytesIO()
    fits.PrimaryHDU(np.zeros((64, 64), np.int16)).writeto(buffer)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("cut", "needle"),
    [
        (lambda b: b"", "empty file"),
        (lambda b: b"hello world" * 300, "not a FITS file"),
        (lambda b: b[:2000], "truncated or damaged FITS file: 2000 bytes"),
        (lambda b: b[: 2880 + 100], "truncated FITS file: 2980 bytes where its header describes 11520"),
        (lambda b: b[:2880], "truncated FITS file: 2880 bytes where its header describes 11520"),
        (lambda b: b.replace(b"END" + b" " * 77, b" " * 80, 1), "no END card"),
    ],
    ids=["empty", "not-fits", "cut-in-the-header", "cut-in-the-data", "header-only", "no-end-card"],
)
def test_centroid_on_a_broken_fits_names_the_damage_not_an_astropy_option(tmp_path, capsys, cut, needle):
    path = tmp_path / "frame.fits"
    path.write_bytes(cut(_fits_bytes()))
    err = error_line(capsys, ["centroid", str(path), "--out", str(tmp_path / "s.csv"), "--time-unknown"])
    assert needle in err
    assert "=True" not in err and "ignore_missing" not in err and "WARNING" not in err  # nothing of astropy's advice


def test_calibrate_given_a_truth_json_says_what_the_file_is(tmp_path, capsys):
    from hostlink.files.truth import write_truth
    from hostlink.sky.simulate import seed004_config, simulate

    truth = tmp_path / "s.truth.json"
    write_truth(truth, simulate(seed004_config(frames=3, seed=1)).truth)
    args = ["--nominal", "builtin:seed004_nominal", "--out", str(tmp_path / "r.json")]
    err = error_line(capsys, ["calibrate", str(truth), *args])
    assert "a simulation truth file" in err and "not a session" in err and "missing required" not in err
    err = error_line(capsys, ["calibrate", str(data_file("seed004_camera.json")), *args])
    assert "a camera parameter file" in err and "--nominal" in err


def test_dask_missing_names_our_distribution_and_extra(tmp_path, capsys, monkeypatch):
    from hostlink.calibration.distributed import dask_client
    from hostlink.errors import UserError

    monkeypatch.setitem(sys.modules, "distributed", None)  # as if Dask were not installed
    with pytest.raises(UserError) as info, dask_client("local"):
        pass
    assert "pip install 'startracker-companion[dask]'" in str(info.value) and "hostlink[" not in str(info.value)


def test_every_install_hint_names_startracker_companion():
    """Every string literal in the package and the docs that says `pip install` names this distribution (or is
    the one helper that builds the hint), and the helper names a real extra of pyproject.toml."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["name"] == DISTRIBUTION and "dask" in project["optional-dependencies"]
    assert install_hint("dask") == "pip install 'startracker-companion[dask]'"
    found = 0
    for path in sorted((ROOT / "hostlink").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and "pip install" in node.value:
                found += 1
                assert DISTRIBUTION in node.value or path.name == "errors.py", f"{path}: {node.value!r}"
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        assert "hostlink[" not in text, f"{path} tells users to install an unrelated project named hostlink"
    assert found >= 1
