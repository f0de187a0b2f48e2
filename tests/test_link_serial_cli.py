"""The whole cycle over a serial link against the emulator process (a pty paced to the baud rate), through the CLI
as a user runs it: stream, upload, params, monitor, accept; refusals and dropped links are one-line errors."""

import json

import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.files.params import data_file, load_params
from hostlink.files.session import read_session
from onboard.banks import params_to_table


@pytest.fixture(scope="module")
def emulator():
    with running_emulator("serial", "--sim-frames", "200") as info:
        yield info


def one_line(text):
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def test_emulator_announces_a_serial_link(emulator):
    assert emulator["link"].startswith("serial:/dev/") and emulator["link"].endswith("@921600")


def test_stream_records_frames_and_counts_no_loss(emulator, tmp_path):
    out = tmp_path / "s.csv"
    run = hostlink("stream", "--link", emulator["link"], "--frames", "40", "--out", str(out))
    assert run.returncode == 0, run.stderr
    assert "lost 0 message(s)" in run.stderr
    session = read_session(out)
    assert session.n_frames == 40 and len(session) >= 40 * 10  # the simulator keeps >= 10 stars per frame


def test_upload_then_params_reads_back_the_file_to_float32(emulator, tmp_path):
    camera = data_file("seed004_camera.json")
    run = hostlink("upload", str(camera), "--link", emulator["link"])
    assert run.returncode == 0, run.stderr
    assert "read back equal" in one_line(run.stderr)
    shown = hostlink("params", "--link", emulator["link"])
    assert shown.returncode == 0, shown.stderr
    printed = tmp_path / "printed.json"
    printed.write_text(shown.stdout)
    assert params_to_table(load_params(printed)) == params_to_table(load_params(camera))
    assert set(json.loads(shown.stdout)) == {
        "focal_length_mm",
        "pixel_pitch_um",
        "principal_point_px",
        "image_size_px",
        "distortion",
    }


def test_a_set_the_sensor_refuses_prints_its_reason_on_one_line(emulator, tmp_path):
    bad = json.loads(data_file("seed004_camera.json").read_text())
    bad["principal_point_px"] = [5000.0, 530.0]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    before = hostlink("params", "--link", emulator["link"]).stdout
    run = hostlink("upload", str(path), "--link", emulator["link"], "--no-host-check")
    assert run.returncode == 4
    line = one_line(run.stderr)
    assert "INVALID_PARAMS" in line and "principal_point_px[0]" in line and "off the detector" in line
    assert hostlink("params", "--link", emulator["link"]).stdout == before  # the old set is still active
    run = hostlink("upload", str(path), "--link", emulator["link"])  # the host's own check refuses first
    assert run.returncode == 2 and "principal_point_px[0]" in one_line(run.stderr)


def test_monitor_shows_the_estimate_and_accept_commits_it(emulator, tmp_path):
    run = hostlink("monitor", "--link", emulator["link"], "--count", "2", "--every-frames", "20", "--json")
    assert run.returncode == 0, run.stderr
    polls = [json.loads(line) for line in run.stdout.splitlines()]
    assert [p["frames_received"] for p in polls] == [20, 40]
    # the sensor runs its estimator on each exposure before streaming it (its budget allows every 1 s frame), and the
    # active set is the true camera, so every frame received has been an update: the count rises with the frames
    assert all(p["updates"] >= p["frames_received"] for p in polls)
    assert set(polls[-1]["values"]) == {"f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "s1", "s2"}
    out = tmp_path / "accepted.json"
    run = hostlink("accept", "--link", emulator["link"], "--out", str(out))
    assert run.returncode == 2 and "not converged" in one_line(run.stderr)  # 40 updates: under the 300 needed
    run = hostlink("accept", "--link", emulator["link"], "--out", str(out), "--force")
    assert run.returncode == 0, run.stderr
    shown = tmp_path / "shown.json"
    shown.write_text(hostlink("params", "--link", emulator["link"]).stdout)
    assert params_to_table(load_params(out)) == params_to_table(load_params(shown))


def test_bad_link_strings_and_missing_ports_are_one_line_errors():
    run = hostlink("params", "--link", "bogus:thing")
    assert run.returncode == 2 and "SCHEME:TARGET" in one_line(run.stderr)
    run = hostlink("params", "--link", "serial:/dev/does-not-exist@9600")
    assert run.returncode == 3 and "cannot open" in one_line(run.stderr)


def test_a_silent_port_times_out_with_one_line():
    import os

    master, slave = os.openpty()  # a port with nobody answering
    try:
        run = hostlink("params", "--link", f"serial:{os.ttyname(slave)}", "--timeout", "0.3")
    finally:
        os.close(master)
        os.close(slave)
    assert run.returncode == 3 and "no reply to READ_ACTIVE" in one_line(run.stderr)


def test_a_link_dropped_mid_stream_is_one_line_and_non_zero(tmp_path):
    import threading

    with running_emulator("serial", "--sim-frames", "50", "--baud", "19200") as info:
        # 19200 baud: ~80 frames/s, so 100000 frames take long enough for the emulator to die mid-stream
        timer = threading.Timer(1.5, info["process"].kill)
        timer.start()
        run = hostlink("stream", "--link", info["link"], "--frames", "100000", "--out", str(tmp_path / "x.csv"))
        timer.cancel()
    assert run.returncode == 3
    line = one_line(run.stderr)
    assert line.startswith("hostlink stream: error: serial:") and ("connection lost" in line or "no " in line)
