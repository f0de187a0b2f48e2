"""``hostlink stream`` from an emulated sensor replaying a file, over every transport (serial, CAN, Modbus TCP and
Modbus RTU framing): the file's rows arrive exactly once each, centroids on the wire's 2^-10 px grid, and frames lost
on the line are counted from the transport's sequence numbers."""

from __future__ import annotations

import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.api import read_session
from protocol.messages import CENTROID_LSB_PX, MAG_LSB

#: (transport, emulator options, the key of its ready line that names the link)
TRANSPORTS = {
    "serial": ("serial", (), "link"),
    "can": ("can", ("--bitrate", "500000"), "link"),
    "modbus-tcp": ("modbus", (), "link"),
    "modbus-rtu": ("modbus", (), "link_rtu"),
}


def _magnitudes_as_the_wire_carries_them(transport: str, got, source) -> None:
    if transport == "serial":
        assert np.array_equal(got.mag, source.mag, equal_nan=True)
    elif transport == "can":
        assert got.mag is None or np.all(np.isnan(got.mag))  # a STAR frame has no room for the magnitude (by design)
    else:
        assert np.allclose(got.mag, source.mag, atol=MAG_LSB / 2, rtol=0, equal_nan=True)  # millimag steps


@pytest.mark.parametrize("name", list(TRANSPORTS))
def test_replay_streams_exactly_the_rows_of_the_file(replay_file, tmp_path, name):
    transport, options, key = TRANSPORTS[name]
    source = read_session(replay_file)
    assert np.any(source.star_id == 0)  # false stars (no identity, no reference direction) are replayed too
    with running_emulator(transport, "--replay", str(replay_file), *options) as info:
        out = tmp_path / "out.csv"
        run = hostlink("stream", "--link", info[key], "--frames", "1000", "--out", str(out))
        assert run.returncode == 0, run.stderr
        assert "stream ended after 50 frames" in run.stderr and "lost 0" in run.stderr
        got = read_session(out)
    assert len(got) == len(source)
    assert np.array_equal(got.frame, source.frame) and np.array_equal(got.star_id, source.star_id)
    assert list(got.t_utc) == list(source.t_utc)
    # fixed point: each coordinate is the file's rounded to the nearest 2^-10 px step (the grid of every transport)
    assert np.max(np.abs(got.x_px - source.x_px)) <= CENTROID_LSB_PX / 2
    assert np.max(np.abs(got.y_px - source.y_px)) <= CENTROID_LSB_PX / 2
    _magnitudes_as_the_wire_carries_them(transport, got, source)


@pytest.mark.parametrize("name", ["serial", "can", "modbus-tcp"])
def test_frames_lost_on_the_line_are_counted_from_sequence_numbers(replay_file, tmp_path, name):
    transport, options, key = TRANSPORTS[name]
    with running_emulator(transport, "--replay", str(replay_file), *options, "--drop-every", "10") as info:
        run = hostlink("stream", "--link", info[key], "--frames", "1000", "--out", str(tmp_path / "o.csv"))
    assert run.returncode == 0, run.stderr
    # frames 10, 20, 30, 40, 50 of the 50 are lost; the end-of-stream message after them reveals the last gap
    assert "45 frames" in run.stderr and "lost 5 message(s)" in run.stderr
