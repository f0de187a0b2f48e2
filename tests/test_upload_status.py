"""A parameter file carries its calibration status, and ``hostlink upload`` never sends a failed or unconverged set
(issue 31): ``calibrate --keep-failed`` (not converged, or most stars rejected) and a ``replay`` that has not
converged write ``status`` and ``status_reason``; their upload is one line, exit 2, before any link is opened, and
the emulated sensor's active set is unchanged. A converged calibration is committed. A file without ``status`` is
read by its older markers (``failed``, ``converged: false``) and otherwise uploaded as a design set."""

import json
from dataclasses import replace

import numpy as np
import pytest
from emulator_fixtures import hostlink

from hostlink.cli import main
from hostlink.emulator.process import EmulatorProcess
from hostlink.files.params import data_file
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate

NOMINAL_PATH = str(data_file("seed004_nominal.json"))
FAST = ("--no-estimator", "--sim-frames", "5")


@pytest.fixture(scope="module")
def sensor(tmp_path_factory):
    flash = tmp_path_factory.mktemp("flash") / "sensor.img"
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:
        yield emulator.link


@pytest.fixture(scope="module")
def session_path(tmp_path_factory):
    """120 frames of the seed 004 camera on the real sky."""
    path = tmp_path_factory.mktemp("session") / "s.csv"
    write_session(path, simulate(seed004_config(frames=120, seed=41)).session)
    return str(path)


def one_line(text):
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def calibrate(session, out, *extra):
    return main(["calibrate", session, "--nominal", NOMINAL_PATH, "--out", str(out), "--quiet", *extra])


def refused_and_unchanged(sensor, path, needle):
    before = hostlink("params", "--link", sensor).stdout
    run = hostlink("upload", str(path), "--link", sensor)
    line = one_line(run.stderr)
    assert run.returncode == 2 and "refused" in line and needle in line and "nothing was sent" in line
    assert hostlink("params", "--link", sensor).stdout == before  # the active set (and its generation) unchanged
    # refused before any link is opened: a link that does not exist is never reached
    run = hostlink("upload", str(path), "--link", "serial:/nonexistent/tty")
    assert run.returncode == 2 and needle in one_line(run.stderr) and "/nonexistent" not in run.stderr


def test_a_converged_calibration_says_so_and_is_committed(sensor, session_path, tmp_path):
    out = tmp_path / "cal.json"
    assert calibrate(session_path, out) == 0
    doc = json.loads(out.read_text())
    assert doc["status"] == "converged" and doc["status_reason"] is None
    run = hostlink("upload", str(out), "--link", sensor)
    assert run.returncode == 0 and "read back equal" in one_line(run.stderr)


def test_an_unconverged_calibration_kept_is_refused(sensor, session_path, tmp_path):
    out = tmp_path / "cal.json"
    assert calibrate(session_path, out, "--max-iter", "1", "--keep-failed") == 2
    doc = json.loads(out.read_text())
    assert doc["status"] == "not_converged" and "did not converge" in doc["status_reason"]
    refused_and_unchanged(sensor, out, "status not_converged")


def test_a_calibration_with_most_stars_rejected_kept_is_refused(sensor, session_path, tmp_path):
    """The issue's case: most identifications wrong (3 frames of 5 with every reference rolled by one star), the
    fit converges on what is left but rejects more than half of the stars: status failed, upload refused."""
    from hostlink.files.session import read_session

    s = read_session(session_path)
    s = replace(s, ra_deg=s.ra_deg.copy(), dec_deg=s.dec_deg.copy())
    starts = s.frame_starts
    for f in range(0, s.n_frames, 5):
        for g in range(f, min(f + 3, s.n_frames)):
            a, b = int(starts[g]), int(starts[g + 1])
            ident = a + np.flatnonzero(s.star_id[a:b] != 0)
            s.ra_deg[ident] = np.roll(s.ra_deg[ident], 1)
            s.dec_deg[ident] = np.roll(s.dec_deg[ident], 1)
    scrambled = tmp_path / "scrambled.csv"
    write_session(scrambled, s)
    out = tmp_path / "cal.json"
    assert calibrate(str(scrambled), out, "--keep-failed") == 2
    doc = json.loads(out.read_text())
    assert doc["status"] == "failed" and "more than 50 %" in doc["status_reason"]
    refused_and_unchanged(sensor, out, "status failed")


def test_a_replay_that_has_not_converged_is_refused(sensor, session_path, tmp_path, capsys):
    """120 frames from the cold-start prior: fewer updates than the sensor's own accept rule needs (its burn-in,
    300), so the estimate is not converged, says why, and is refused like a failed calibration."""
    out = tmp_path / "onboard.json"
    assert main(["replay", session_path, "--nominal", NOMINAL_PATH, "--out", str(out)]) == 0
    assert "upload refuses this file" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["status"] == "not_converged" and "updates" in doc["status_reason"]
    refused_and_unchanged(sensor, out, "status not_converged")


def test_a_long_replay_converges(tmp_path):
    """1000 frames (the README's worked session): the estimate passes the accept rule."""
    session = tmp_path / "s.csv"
    write_session(session, simulate(seed004_config(frames=1000, seed=3)).session)
    out = tmp_path / "onboard.json"
    assert main(["replay", str(session), "--nominal", NOMINAL_PATH, "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["status"] == "converged" and doc["status_reason"] is None


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        ({"failed": "the fit did not converge in 1 iterations"}, "status failed"),
        ({"converged": False}, "status not_converged"),
    ],
    ids=["legacy-failed", "legacy-converged-false"],
)
def test_a_file_from_before_the_status_key_is_read_by_its_older_markers(sensor, tmp_path, extra, needle):
    doc = dict(json.loads(data_file("seed004_camera.json").read_text()), **extra)
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    refused_and_unchanged(sensor, path, needle)


def test_an_unknown_status_is_refused_not_read_as_converged(tmp_path):
    doc = dict(json.loads(data_file("seed004_camera.json").read_text()), status="maybe")
    path = tmp_path / "odd.json"
    path.write_text(json.dumps(doc))
    run = hostlink("upload", str(path), "--link", "serial:/nonexistent/tty")
    assert run.returncode == 2 and "status: expected one of converged" in one_line(run.stderr)
