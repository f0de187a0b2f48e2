"""What a user gets from ``pip install``: an sdist that carries the docs, the licence and the tests, a wheel built from
it, and, installed into a fresh virtual environment outside the checkout, the README's worked session run end to end
from the package alone (``hostlink example``, then the commands of its README.txt).

Slow (a virtual environment and an install of the dependencies, from pip's configured index and cache) but part of
CI: it is the only test that sees the package as a user does, without the checkout on the path."""

import csv
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Folders of a working tree that are not the project's source.
_NOT_SOURCE = (".git", ".venv*", "build", "dist", "*.egg-info", "__pycache__", ".*cache", "bench-report", ".team")
#: Each step's deadline [s]: an install on a loaded 2-core machine takes ~20 s; this only stops a hung step.
STEP_TIMEOUT_S = 300


def _run(args, cwd, env=None):
    run = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=STEP_TIMEOUT_S)
    assert run.returncode == 0, f"{' '.join(map(str, args))}\n{run.stdout}\n{run.stderr}"
    return run


def _user_env(venv: Path) -> dict[str, str]:
    """A shell with the fresh environment first on PATH and nothing pointing into the checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "HOSTLINK_DEBUG")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)
    env["MPLBACKEND"] = "Agg"
    env["XDG_CACHE_HOME"] = str(venv.parent / "cache")  # the catalogue cache of this user, not the developer's
    return env


@pytest.mark.slow
def test_a_wheel_installed_outside_the_checkout_runs_the_worked_session(tmp_path):
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(*_NOT_SOURCE))  # the checkout is never written to
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], tmp_path)
    py = str(venv / "bin" / "python")
    pip = [py, "-m", "pip", "--disable-pip-version-check", "--quiet"]
    env = _user_env(venv)

    # the sdist: docs, licence, tests and scripts travel with the source
    _run([*pip, "install", "build"], tmp_path, env)
    dist = tmp_path / "dist"
    _run([py, "-m", "build", "--sdist", "--outdir", str(dist), str(src)], tmp_path, env)
    (sdist,) = dist.glob("*.tar.gz")
    with tarfile.open(sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    for needed in (
        "LICENSE",
        "README.md",
        "CHANGELOG.md",
        "docs/camera-model.md",
        "docs/commands.md",
        "docs/hardware.md",
        "docs/modbus_map.md",
        "protocol/startracker.dbc",
        "protocol/modbus_map.json",
        "hostlink/data/seed004_nominal.json",
        "tests/emulator_fixtures.py",
        "scripts/test.sh",
    ):
        assert needed in names, f"{needed} missing from {sdist.name}"

    # the wheel, built from the sdist as pip would, then installed with its dependencies
    _run([*pip, "wheel", "--no-deps", "--wheel-dir", str(dist), str(sdist)], tmp_path, env)
    (wheel,) = dist.glob("*.whl")
    _run([*pip, "install", str(wheel)], tmp_path, env)

    work = tmp_path / "user"
    work.mkdir()
    where = _run([py, "-c", "import hostlink, protocol, onboard; print(hostlink.__file__)"], work, env).stdout
    assert Path(where.strip()).is_relative_to(venv), where  # the installed package, not the checkout
    assert _run(["hostlink", "--version"], work, env).stdout.strip() == f"hostlink {version}"
    # package data reachable by name: the DBC and the Modbus map come with the wheel
    _run([py, "-c", "from protocol.modbus_map import load_map; load_map()"], work, env)

    _run(["hostlink", "example", "session"], work, env)
    session = work / "session"
    commands = [line.strip() for line in (session / "README.txt").read_text().splitlines()]
    commands = [c for c in commands if c.startswith("hostlink ") and "--link" not in c and "emulate" not in c]
    assert [c.split()[1] for c in commands] == ["simulate", "calibrate", "replay", "attitude"]
    for command in commands:
        _run(command.split(), session, env)

    truth = json.loads((session / "s.truth.json").read_text())["camera"]
    cal = json.loads((session / "cal.json").read_text())
    f_error = cal["focal_length_mm"] - truth["focal_length_mm"]
    # the worked session calibrates: within 5 sigma of the truth (a correct estimator misses by more 1 in 1.7 million)
    assert abs(f_error) < 5 * cal["sigma"]["focal_length_mm"], (f_error, cal["sigma"]["focal_length_mm"])
    assert (session / "plots").is_dir() and any((session / "plots").glob("*.png"))
    onboard = json.loads((session / "onboard.json").read_text())
    assert abs(onboard["focal_length_mm"] - truth["focal_length_mm"]) < 5 * onboard["sigma"]["focal_length_mm"]
    with open(session / "attitude.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == truth_frames(session) and all(r["status"] == "ok" for r in rows)
    # the documentation pages come with the wheel, where `hostlink --docs` says
    docs = Path(_run(["hostlink", "--docs"], work, env).stdout.splitlines()[0])
    assert docs.is_relative_to(venv) and (docs / "interfaces.md").is_file() and (docs.parent / "CHANGELOG.md").is_file()


def truth_frames(session: Path) -> int:
    return int(json.loads((session / "s.truth.json").read_text())["frames"])


def test_the_readme_worked_session_is_the_one_hostlink_example_writes():
    """The README shows the commands README.txt lists, so a user following either runs the same session."""
    from hostlink.mission.example import NEXT_COMMANDS

    readme = (ROOT / "README.md").read_text()
    for command in NEXT_COMMANDS:
        assert re.search(re.escape(command.replace("hostlink ", "", 1)), readme), command
