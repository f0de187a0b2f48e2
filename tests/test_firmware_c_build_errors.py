"""The C firmware core's build (hostlink/portkit/firmware_c.py) when the machine's tools fail: a compiler that exits
non-zero without a word, one that exits 0 but writes no library, and a cache directory that cannot be created are
each a one-line UserError (exit 2 from the commands), never an internal error with a traceback."""

import os
import shutil
import subprocess
import sys

import pytest

from hostlink.errors import UserError
from hostlink.portkit import firmware_c

FALSE = shutil.which("false")
TRUE = shutil.which("true")


@pytest.mark.skipif(FALSE is None, reason="no false(1) on this machine")
def test_a_compiler_that_fails_silently_is_named_with_its_exit_status(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", FALSE)
    with pytest.raises(UserError, match=r"did not compile with .*false: exit status 1, no message"):
        firmware_c.build_library(tmp_path)
    assert not list(tmp_path.glob("*.so"))


@pytest.mark.skipif(TRUE is None, reason="no true(1) on this machine")
def test_a_compiler_that_writes_no_library_is_an_error_not_a_rename_failure(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", TRUE)
    with pytest.raises(UserError, match="it wrote no library"):
        firmware_c.build_library(tmp_path)
    assert not list(tmp_path.glob("*.so"))


def test_an_unusable_cache_directory_is_a_one_line_error_from_emulate(tmp_path):
    if TRUE is None:
        pytest.skip("no true(1) on this machine")
    blocker = tmp_path / "cache"
    blocker.write_text("a file where the cache directory should be")
    env = {**os.environ, "XDG_CACHE_HOME": str(blocker), "CC": TRUE}
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", "emulate", "--transport", "serial", "--firmware", "c"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert run.returncode == 2, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "cannot build the C firmware core in" in run.stderr and "Not a directory" in run.stderr


def test_bench_with_the_c_firmware_and_no_compiler_stops_before_simulating(tmp_path, monkeypatch, capsys):
    from hostlink.cli import main

    monkeypatch.setenv("CC", "no-such-compiler")
    out = tmp_path / "bench"
    assert main(["bench", "--firmware", "c", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no C compiler found ('no-such-compiler' is not on PATH)" in err[0], err
    assert not out.exists() or not any(out.iterdir())  # no session, flash image or report written
