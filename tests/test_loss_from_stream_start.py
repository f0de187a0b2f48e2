"""Loss counted from the stream's start (issue 33), in process, without timing: the frames lost before the first one
received are counted on serial (stream sequence numbers from 0), on CAN (from the first frame counter the start's ACK
carries) and on Modbus (window_seq from 1); the emulated sensor acknowledges a start with its first frame counter."""

import os
import shutil

import pytest
from register_fakes import ImageRegisterClient
from stream_frames import NOMINAL, one_star_frame

from hostlink.emulator.modbus_endpoint import RegisterSensor
from hostlink.emulator.sensor import EmulatedSensor, SourceFrame
from hostlink.links import open_link
from hostlink.links.can_link import StreamAssembler
from hostlink.links.modbus_link import ModbusLink
from onboard import banks
from onboard.firmware import Firmware
from protocol import can_frames as cf
from protocol import messages as m
from protocol.framing import encode_frame


def _frame(k: int) -> m.CentroidFrame:
    return one_star_frame(k)


def _sensor(first: int = 0, n: int = 10) -> EmulatedSensor:
    source = (SourceFrame(frame=_frame(k), r_ref=None) for k in range(first, first + n))
    return EmulatedSensor(Firmware(banks.factory_store(NOMINAL), None), source)


def test_serial_counts_the_frames_lost_before_the_first_one_received():
    link = open_link("serial:loop://", timeout_s=0.5)
    link._reset_loss_counting()  # what set_streaming(True) does before the start goes out
    # the stream's messages 0..2 were lost on the line; 3 and 4 arrive, then 7
    link._port.write(b"".join(encode_frame(seq, m.encode(_frame(100 + seq))) for seq in (3, 4, 7)))
    seen = [(link.recv_frame().frame, link.stats.lost_messages) for _ in range(3)]
    assert seen == [(103, 3), (104, 3), (107, 5)]
    link.close()


def _can_frames(frames: list[m.CentroidFrame]) -> list[tuple[int, bytes]]:
    enc = cf.StreamEncoder()
    return [f for frame in frames for f in enc.encode(frame)]


def test_can_counts_from_the_first_frame_counter_the_start_acknowledged():
    asm = StreamAssembler()
    asm.forget_sequence()
    asm.begin_at(10)  # the ACK came before any frame (the sensor acknowledges, then streams)
    got = [asm.feed(fid, data) for fid, data in _can_frames([_frame(13), _frame(14), _frame(16)])]
    assert [g.frame for g in got if isinstance(g, m.CentroidFrame)] == [13, 14, 16]
    assert asm.lost == 3 + 1  # 10..12 before the first received, 15 between


def test_can_frames_before_a_late_ack_count_from_the_start_and_an_older_stream_is_dropped():
    asm = StreamAssembler()
    asm.forget_sequence()  # what set_streaming(True) does before the start goes out
    # a frame of a stream stopped just before (counter 5), then frames 12 and 13 of the new stream, which began at
    # 10, all before the ACK reached the host (the first ACK was lost, the repeated start's ACK came after them)
    for fid, data in _can_frames([_frame(5), _frame(12), _frame(13)]):
        asm.feed(fid, data)
    asm.begin_at(10)
    asm.begin_at(10)  # the same ACK again: changes nothing
    assert asm.lost_at_start == asm.lost == 2  # 10 and 11
    assert asm.is_stale(_frame(5)) and not asm.is_stale(_frame(12))
    late = [asm.feed(fid, data) for fid, data in _can_frames([_frame(4), _frame(15)])]
    assert [g.frame for g in late if isinstance(g, m.CentroidFrame)] == [15]  # the old stream's 4 is not delivered
    assert asm.lost == 2 + 1  # 14; the stale frame is neither lost nor delivered


def _c_sensor(first: int, n: int = 10) -> EmulatedSensor:
    from hostlink.portkit.firmware_c import CFirmware

    source = (SourceFrame(frame=_frame(k), r_ref=None) for k in range(first, first + n))
    firmware = CFirmware(banks.RamFlash(), banks.seeded_identity(0), None, NOMINAL, with_estimator=False)
    return EmulatedSensor(firmware, source)


@pytest.mark.parametrize("firmware", ["python", "c"])
def test_the_start_is_acknowledged_with_its_first_frame_counter_and_a_repeated_start_changes_nothing(firmware):
    """The firmware (Python model or C core) forms the ACK; the emulated camera only announces its next counter."""
    if firmware == "c" and shutil.which(os.environ.get("CC") or "cc") is None:
        pytest.skip("no C compiler")
    sensor = _sensor(first=40) if firmware == "python" else _c_sensor(first=40)
    ack = sensor.handle(m.StreamControl(tag=1, enable=True))
    assert isinstance(ack, m.Ack) and ack.value == 40 and sensor.streams_started == 1
    assert sensor.next_stream_message().frame == 40  # the exposure acknowledged is the one sent first
    again = sensor.handle(m.StreamControl(tag=1, enable=True))  # the ACK was lost: the host asks again
    assert again.value == 40 and sensor.streams_started == 1
    assert sensor.next_stream_message().frame == 41
    sensor.handle(m.StreamControl(tag=2, enable=False))
    assert sensor.handle(m.StreamControl(tag=3, enable=True)).value == 42 and sensor.streams_started == 2


def test_modbus_numbers_a_new_stream_from_its_start_and_counts_a_first_message_lost():
    sensor = _sensor(first=0)
    image = RegisterSensor(sensor, drop_every=2)  # test hook: every 2nd message numbered and not shown
    link = ModbusLink(ImageRegisterClient(image), "modbus-tcp:fake:1", timeout_s=0.5)
    link.set_streaming(True)
    assert (link.recv_frame().frame, link.stats.lost_messages) == (0, 0)  # window_seq 1
    assert (link.recv_frame().frame, link.stats.lost_messages) == (2, 1)  # seq 2 (frame 1) dropped
    link.set_streaming(False)
    link.set_streaming(True)  # a new stream: numbered from its start again, its counters reset
    assert (link.recv_frame().frame, link.stats.lost_messages) == (3, 0)  # the next exposure, seq 1
    assert (link.recv_frame().frame, link.stats.lost_messages) == (5, 1)
