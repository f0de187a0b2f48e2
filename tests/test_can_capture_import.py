"""``hostlink import-can``: a CAN capture (python-can's Logger: BLF, ASC, CSV) of a sensor's stream becomes the same
session ``hostlink stream`` records from that bus; incomplete frames are dropped and counted; captures that cannot be
one session are refused in one line."""

import threading
import time

import can
import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.errors import UserError
from hostlink.files.session import read_session, write_session
from hostlink.links.can_capture import read_can_capture
from hostlink.links.can_link import open_bus, parse_target
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from protocol import can_frames as cf
from protocol.messages import CentroidFrame, StreamControl

BITRATE = "500000"
#: Generous deadline for an observable event on a shared 2-core machine [s].
DEADLINE_S = 60.0


@pytest.fixture(scope="module")
def replay_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "session.csv"
    sim = simulate(SimConfig(camera=seed004_camera(), frames=40, noise_px=0.01, seed=5, false_star_fraction=0.1))
    write_session(path, sim.session)
    return path


class _EndOfStreamSeen(can.Listener):
    """Sets ``event`` when the sensor's END_OF_STREAM frame passes: every stream frame before it has been logged."""

    def __init__(self) -> None:
        self.event = threading.Event()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == cf.END_OF_STREAM.frame_id:
            self.event.set()

    def stop(self) -> None:  # abstract in python-can 4.4
        pass


def _join_bus(bus: can.BusABC) -> None:
    """Wait until the emulated bus delivers to this node: ask the sensor to stop a stream that is not running and
    wait for its ACK (a single frame every node receives)."""
    tag = 0x5EED
    fid, data = cf.encode_single(StreamControl(tag=tag, enable=False))
    bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        msg = bus.recv(1.0)
        if msg is not None and msg.arbitration_id == cf.ACK.frame_id:
            if cf.decode_single(msg.arbitration_id, bytes(msg.data)).tag == tag:
                return
    raise AssertionError("the logger never received the sensor's ACK")


def test_a_blf_and_an_asc_capture_of_a_live_stream_import_to_the_session_hostlink_stream_wrote(replay_file, tmp_path):
    blf, asc = tmp_path / "capture.blf", tmp_path / "capture.asc"
    streamed = tmp_path / "streamed.csv"
    with running_emulator("can", "--replay", str(replay_file), "--bitrate", BITRATE) as info:
        bus = open_bus(parse_target(info["link"].split(":", 1)[1]))
        try:
            _join_bus(bus)
            end = _EndOfStreamSeen()
            writers = [can.Logger(str(blf)), can.Logger(str(asc))]
            notifier = can.Notifier(bus, [*writers, end])
            try:
                run = hostlink("stream", "--link", info["link"], "--frames", "1000", "--out", str(streamed))
                assert end.event.wait(DEADLINE_S), "the logger never saw END_OF_STREAM"
            finally:
                notifier.stop()  # stops (flushes and closes) every listener too
        finally:
            bus.shutdown()
    assert run.returncode == 0, run.stderr
    assert "stream ended after 40 frames" in run.stderr and "lost 0" in run.stderr
    for capture in (blf, asc):
        out = tmp_path / f"imported-{capture.suffix[1:]}.csv"
        imp = hostlink("import-can", str(capture), "--out", str(out))
        assert imp.returncode == 0, imp.stderr
        assert "40 frames" in imp.stderr and "dropped 0 incomplete" in imp.stderr and "0 corrupt" in imp.stderr
        # the same decoder and the same writer: the imported session is the streamed one, byte for byte
        assert out.read_bytes() == streamed.read_bytes(), capture.suffix
    assert len(read_session(streamed)) == len(read_session(replay_file))


def _stream_messages(frames: list[CentroidFrame], t0_s: float = 100.0, channel=0) -> list[can.Message]:
    """The CAN frames a sensor sends for these centroid frames (protocol.can_frames.StreamEncoder)."""
    out = []
    encoder = cf.StreamEncoder()
    for f in frames:
        for fid, data in encoder.encode(f):
            out.append(
                can.Message(
                    timestamp=t0_s + 1e-3 * len(out),
                    arbitration_id=fid,
                    data=data,
                    is_extended_id=False,
                    channel=channel,
                )
            )
    return out


def _frame(number: int, n_stars: int) -> CentroidFrame:
    k = np.arange(n_stars)
    return CentroidFrame(
        frame=number,
        t_us=1_773_454_200_000_000 + 250_000 * number,  # 2026-03-14T02:10:00Z + 0.25 s per frame
        star_id=(1000 + 7 * k + number).astype(np.uint32),
        x_px=(10.0 + 100.5 * k + number / 1024).astype(np.float64),
        y_px=(1000.0 - 50.25 * k - number / 512).astype(np.float64),
        mag=np.full(n_stars, np.nan),
    )


def _write_log(path, messages) -> None:
    with can.Logger(str(path)) as log:
        for m in messages:
            log.on_message_received(m)


@pytest.mark.parametrize("suffix", [".csv", ".asc", ".blf"])
def test_incomplete_frames_are_dropped_and_counted_and_other_traffic_is_ignored(tmp_path, suffix):
    frames = [_frame(0, 3), _frame(1, 4), _frame(3, 2), _frame(4, 0), _frame(5, 5)]
    msgs = _stream_messages(frames)
    header_1 = next(i for i, m in enumerate(msgs) if m.arbitration_id == cf.FRAME_HEADER.frame_id and m.data[0] == 1)
    del msgs[header_1 + 2]  # frame 1 loses its second star
    msgs.insert(3, can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False, timestamp=100.0025))
    msgs.insert(5, can.Message(arbitration_id=0x101, data=bytes(8), is_extended_id=True, timestamp=100.0045))
    del msgs[-3:]  # the capture ends in the middle of frame 5
    path = tmp_path / f"capture{suffix}"
    _write_log(path, msgs)
    got = read_can_capture(path)
    assert [f.frame for f in got.frames] == [0, 3, 4]
    assert (got.incomplete, got.counter_gaps, got.corrupt) == (2, 1, 0)  # frames 1 and 5 cut; frame 2 never sent
    for a, b in zip(got.frames, (frames[0], frames[2], frames[3]), strict=True):
        assert a.t_us == b.t_us
        assert np.array_equal(a.star_id, b.star_id)
        # on the 2**-10 px grid the wire carries exactly
        assert np.array_equal(a.x_px, b.x_px) and np.array_equal(a.y_px, b.y_px)


def test_captures_that_cannot_be_one_session_are_refused_in_one_line(tmp_path):
    backwards = tmp_path / "restart.asc"
    _write_log(backwards, _stream_messages([_frame(7, 2), _frame(8, 2)]) + _stream_messages([_frame(0, 2)], 200.0))
    two_channels = tmp_path / "two.asc"
    _write_log(two_channels, _stream_messages([_frame(0, 2)], channel=0) + _stream_messages([_frame(1, 2)], channel=1))
    quiet = tmp_path / "quiet.blf"
    _write_log(quiet, [can.Message(arbitration_id=0x7E0, data=bytes(8), is_extended_id=False, timestamp=1.0)])
    garbage = tmp_path / "garbage.blf"
    garbage.write_bytes(b"not a BLF file at all" * 10)
    unknown = tmp_path / "capture.xyz"
    unknown.write_text("1 2 3\n")
    cases = {
        str(backwards): "goes back from 8 to 0",
        str(two_channels): "choose one with --channel",
        str(quiet): "no complete star-sensor frame",
        str(garbage): "garbage.blf",
        str(unknown): "capture.xyz",
        str(tmp_path / "missing.blf"): "no such file",
    }
    for log, text in cases.items():
        run = hostlink("import-can", log, "--out", str(tmp_path / "out.csv"))
        assert run.returncode == 2, (log, run.stderr)
        assert text in run.stderr and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert not (tmp_path / "out.csv").exists()
    # --channel picks one sensor's stream out of a two-channel capture
    got = read_can_capture(two_channels, channel="1")
    assert [f.frame for f in got.frames] == [1]
    with pytest.raises(UserError, match="on channel 5"):
        read_can_capture(two_channels, channel="5")
