"""Against real emulator processes: a sensor that dies mid-stream and a user who presses Ctrl-C both end `hostlink
stream` with one line and a non-zero exit code, and the frames that did arrive are written (nothing lost)."""

import signal
import subprocess
import time

import pytest
from emulator_fixtures import _CLI, _env, running_emulator

from hostlink.files.session import read_session

#: How long to wait for the first frame to reach the stream's file [s]: only a bound for a machine that never
#: delivers (the wait ends as soon as a frame is written; start-up on a loaded 2-core machine takes a few seconds).
_FIRST_FRAME_WAIT_S = 120.0
#: --timeout of the stream; the command must end within it after the sensor died, plus start-up and write time [s].
_TIMEOUT_S = 3.0
_GRACE_S = 15.0


def _wait_for_written_frames(out, proc: subprocess.Popen) -> None:
    """Until the stream's partial file holds a data row (``hostlink stream`` writes each frame as it arrives)."""
    deadline = time.monotonic() + _FIRST_FRAME_WAIT_S
    while time.monotonic() < deadline and proc.poll() is None:
        # the partial file is created exclusively under a random name beside OUT (.OUT.<random>.partial)
        for partial in out.parent.glob(f".{out.name}.*.partial"):
            if partial.read_text().count("\n") >= 2:
                return
        time.sleep(0.05)
    raise AssertionError(f"no frame reached a partial file of {out} ({proc.poll()=})")


def _as_in_a_terminal() -> None:
    """A terminal delivers Ctrl-C to a process whose SIGINT is at its default. A harness started in the background
    (nohup, a CI runner's job) may ignore SIGINT, and a child inherits that: Python then installs no KeyboardInterrupt
    handler. Reset it so the test models the user at a terminal, whatever started the suite."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_stream(link: str, out) -> subprocess.Popen:
    return subprocess.Popen(
        [
            *_CLI,
            "stream",
            "--link",
            link,
            "--frames",
            "1000000",
            "--out",
            str(out),
            "--quiet",
            "--timeout",
            str(_TIMEOUT_S),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        preexec_fn=_as_in_a_terminal,
    )


@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_sensor_dying_mid_stream_is_one_line_exit_3_and_the_frames_received_are_written(transport, tmp_path):
    out = tmp_path / "s.csv"
    with running_emulator(transport, "--sim-frames", "20") as info:
        proc = _start_stream(info["link"], out)
        _wait_for_written_frames(out, proc)
        info["process"].kill()
        _, err = proc.communicate(timeout=_GRACE_S)
    assert proc.returncode == 3, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "frames received before were written" in err, err
    assert len(read_session(out).frame_starts) > 0


def test_ctrl_c_during_stream_writes_the_frames_received_and_exits_130(tmp_path):
    out = tmp_path / "s.csv"
    with running_emulator("serial", "--sim-frames", "20") as info:
        proc = _start_stream(info["link"], out)
        _wait_for_written_frames(out, proc)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=_GRACE_S)
    assert proc.returncode == 130, err
    assert len(err.strip().splitlines()) == 1 and "interrupted" in err, err
    assert len(read_session(out).frame_starts) > 0


def test_modbus_wrong_unit_id_is_one_line_naming_the_unit():
    from emulator_fixtures import hostlink

    with running_emulator("modbus") as info:
        link = info["link"].split(",")[0] + ",unit=7"
        r = hostlink("params", "--link", link, "--timeout", str(_TIMEOUT_S))
    assert r.returncode == 3, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "unit 7" in r.stderr, r.stderr
