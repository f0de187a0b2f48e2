"""The emulated CAN bus (SLCAN over TCP): python-can's own slcan interface talks to it like to an adapter, frames reach
every other node, the bus is never faster than its bit rate, arbitration follows the identifiers, and a node at the
wrong bit rate never joins."""

import socket
import threading
import time

import can
import pytest

from hostlink.emulator.slcan_hub import HubFrame, SlcanHub, format_slcan_frame, parse_slcan_frame
from hostlink.errors import UserError
from hostlink.links.can_link import CanTarget, parse_target
from protocol.can_frames import frame_bits_worst_case


@pytest.fixture()
def hub():
    h = SlcanHub(500_000).start()
    yield h
    h.stop()


def _slcan(hub, **kw):
    return can.Bus(interface="slcan", channel=hub.url, sleep_after_open=0, **kw)


#: Identifier of the frames that prove a TCP node has joined (above every identifier the tests send).
PROBE_ID = 0x7FF
#: Seconds to wait for a TCP node to join: the hub's thread accepts it and reads its open command, which a loaded
#: machine may delay far beyond the microseconds it takes alone; reaching the deadline fails the test.
JOIN_DEADLINE_S = 30.0
#: Seconds of quiet that mean no probe is still on its way.
QUIET_S = 0.3


def _joined(sender, receiver) -> None:
    """Return once ``receiver`` (a TCP node) receives what ``sender`` sends: probe frames until one arrives, then the
    late ones drained. Replaces a fixed sleep that raced the hub's thread."""
    deadline = time.monotonic() + JOIN_DEADLINE_S
    while time.monotonic() < deadline:
        sender.send(can.Message(arbitration_id=PROBE_ID, data=b"", is_extended_id=False))
        msg = receiver.recv(QUIET_S)
        if msg is not None and msg.arbitration_id == PROBE_ID:
            while (late := receiver.recv(QUIET_S)) is not None:
                assert late.arbitration_id == PROBE_ID, late
            return
    raise AssertionError(f"the TCP node did not join the bus within {JOIN_DEADLINE_S} s")


def test_slcan_lines_round_trip():
    for frame in (
        HubFrame(0x101, False, False, 8, bytes(range(8))),
        HubFrame(0x1ABCDEF0, True, False, 2, b"\x01\xff"),
        HubFrame(0x7FF, False, True, 3, b""),
        HubFrame(0x0, False, False, 0, b""),
    ):
        line = format_slcan_frame(frame)
        assert line.endswith(b"\r") and parse_slcan_frame(line[:-1]) == frame
    for bad in (b"t12", b"t1238001122", b"tXYZ0", b"t8001", b"t1239" + b"00" * 9, b"d1238" + b"00" * 8, b""):
        assert parse_slcan_frame(bad) is None


def test_python_can_slcan_node_and_in_process_node_exchange_frames(hub):
    sensor = hub.attach("sensor")
    host = _slcan(hub, bitrate=500_000)
    try:
        _joined(sensor, host)
        sensor.send(can.Message(arbitration_id=0x101, data=bytes(range(8)), is_extended_id=False))
        msg = host.recv(2.0)
        assert msg is not None and msg.arbitration_id == 0x101 and bytes(msg.data) == bytes(range(8))
        host.send(can.Message(arbitration_id=0x1234567, data=b"\x05", is_extended_id=True))
        msg = sensor.recv(2.0)
        assert msg is not None and msg.is_extended_id and msg.arbitration_id == 0x1234567 and msg.data == b"\x05"
    finally:
        host.shutdown()
        sensor.shutdown()


def test_the_bus_is_never_faster_than_its_bit_rate(hub):
    sensor = hub.attach("sensor")
    host = _slcan(hub)
    n = 400
    try:
        _joined(sensor, host)
        bits_before = hub.bits_on_bus
        start = time.monotonic()
        threading.Thread(
            target=lambda: [
                sensor.send(can.Message(arbitration_id=0x101, data=bytes(8), is_extended_id=False), timeout=5)
                for _ in range(n)
            ],
            daemon=True,
        ).start()
        got = 0
        while got < n and (msg := host.recv(2.0)) is not None:
            got += msg.arbitration_id == 0x101
        elapsed = time.monotonic() - start
    finally:
        host.shutdown()
        sensor.shutdown()
    assert got == n
    # the virtual bus delivers frame k no earlier than k worst-case frame times after the first started; the first
    # frame itself may start at once, so n - 1 frame times is the lower bound (delivery jitter only adds)
    assert elapsed >= (n - 1) * frame_bits_worst_case(8, False) / 500_000
    assert hub.bits_on_bus - bits_before == n * 135


def test_lowest_identifier_wins_arbitration_among_pending_frames():
    # slow bus: the first frame takes 13.5 ms, so both later ones are pending when it ends. The frames are queued
    # before the hub's thread starts, so that thread cannot take the CPU between the three sends.
    hub = SlcanHub(10_000)
    a, b, listener = hub.attach("a"), hub.attach("b"), hub.attach("listener")
    try:
        a.send(can.Message(arbitration_id=0x300, data=bytes(8), is_extended_id=False))
        a.send(can.Message(arbitration_id=0x200, data=b"a", is_extended_id=False))
        b.send(can.Message(arbitration_id=0x100, data=b"b", is_extended_id=False))
        hub.start()
        order = [listener.recv(2.0).arbitration_id for _ in range(3)]
    finally:
        for bus in (a, b, listener):
            bus.shutdown()
        hub.stop()
    assert order == [0x300, 0x100, 0x200]


def test_a_node_at_another_bit_rate_never_joins_the_bus(hub):
    sock = socket.create_connection((hub.host, hub.port), timeout=2)
    try:
        sock.sendall(b"S4\rO\r")  # 125 kbit/s on a 500 kbit/s bus
        replies = b""
        while len(replies) < 2:
            replies += sock.recv(16)
        assert replies == b"\x07\x07"  # both refused with BELL
        sock.sendall(b"S6\rO\rV\r")
        replies = b""
        while not replies.endswith(b"V1013\r"):
            replies += sock.recv(16)
        assert replies == b"\r\rV1013\r"
    finally:
        sock.close()


def test_can_link_strings_name_any_python_can_interface():
    assert parse_target("slcan:socket://127.0.0.1:5000@500000") == CanTarget(
        "slcan", "socket://127.0.0.1:5000", 500_000
    )
    assert parse_target("socketcan:can0") == CanTarget("socketcan", "can0", None)
    t = parse_target("pcan:PCAN_USBBUS1@250000,fd=false,tty_baudrate=115200")
    assert t.bitrate == 250_000 and t.options == {"fd": False, "tty_baudrate": 115200}
    assert parse_target("virtual:test").bitrate == 500_000
    for bad in ("slcan", "slcan:", ":can0", "socketcan:can0,novalue"):
        with pytest.raises(UserError):
            parse_target(bad)
