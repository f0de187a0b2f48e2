"""The console script: every documented command is listed, and user errors are one line with a non-zero exit."""

import subprocess
import sys

from hostlink.cli import COMMANDS, main


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hostlink.cli", *args], capture_output=True, text=True)


def test_help_lists_every_documented_command():
    out = _run("--help")
    assert out.returncode == 0
    for name in ("bench", "simulate", "calibrate", "replay", "attitude", "emulate", "stream", "upload", "params"):
        assert name in COMMANDS
        assert name in out.stdout, f"hostlink --help does not list {name}"


def test_unknown_option_is_one_line_error():
    out = _run("--bogus")
    assert out.returncode == 2
    assert len(out.stderr.strip().splitlines()) == 1


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
