"""On a noisy line the Modbus link reads the stream window's head in several chunks, each made again until it
arrives. It used to read every chunk of the head even when the first one (the state register) showed the window
empty, and judged "no centroid frame within the timeout" by the clock when that read returned: at three times the
default fault rates one such poll took 2-9 s, and a stream whose sensor was streaming ended with that LinkError
(scripts/link_faults.py --both-directions --drop 0.03 --ber 3e-4, seeds 11 and 12; docs/links.md), as did a frame's
state flipped to "empty" by a bit error (Modbus TCP has no checksum) in a read begun after the deadline. Now a poll
reads the window's fixed registers and their check alone, an empty window counts only when that check holds, and
only a read begun after the deadline that finds it so ends the wait.

The in-process tests run the link on the register image behind a scripted line whose every exchange takes a fixed
time on a fake clock (no timing of the host); the last one streams from the emulator over the real pymodbus client
and server with the smallest chunk size, so the head of every frame is read in pieces."""

from __future__ import annotations

import pytest
from emulator_fixtures import running_emulator
from register_fakes import ImageRegisterClient
from stream_frames import NOMINAL

from hostlink.emulator.modbus_endpoint import RegisterSensor
from hostlink.emulator.sensor import EmulatedSensor
from hostlink.errors import LinkError
from hostlink.links import modbus_link, open_link
from hostlink.links.modbus_link import _MIN_CHUNK, ModbusLink
from onboard import banks
from onboard.firmware import Firmware

#: Time one exchange takes on the scripted line [s]: long enough that reading a whole head in chunks of _MIN_CHUNK
#: registers (15 chunks) takes five times the link timeout, as on the line that failed (one took 2-9 s).
LINE_S = 0.7
TIMEOUT_S = 2.0


class _Clock:
    """A fake ``time`` for modbus_link: monotonic() and sleep() on a counter the scripted line advances."""

    def __init__(self) -> None:
        self.t = 0.0

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += seconds


class _SlowLine(ImageRegisterClient):
    """A RegisterClient straight on the emulator's register image (a sensor with nothing to stream: its window is
    empty, or once streaming holds the end of the stream), each exchange taking LINE_S on ``clock``; ``reads`` lists
    (start time, address, count). ``damage_state`` reads of the window's first register come back with the state
    flipped to 0 ("no message"), as a bit error on a line without a checksum would give."""

    def __init__(self, clock: _Clock) -> None:
        super().__init__(RegisterSensor(EmulatedSensor(Firmware(banks.factory_store(NOMINAL), None), iter(()))))
        self.clock = clock
        self.reads: list[tuple[float, int, int]] = []
        self.damage_state = 0

    def read(self, table: str, address: int, count: int) -> list[int]:
        self.reads.append((self.clock.t, address, count))
        self.clock.t += LINE_S
        words = self.image.on_read(table, address, count)
        if self.damage_state and table == "input" and address == self.image.map["window_state"].address:
            self.damage_state -= 1
            words = [0, *words[1:]]
        return words

    def write(self, address: int, values: list[int]) -> None:
        self.clock.t += LINE_S
        self.image.on_write(address, values)


def _scripted_link(monkeypatch) -> tuple[ModbusLink, _SlowLine]:
    clock = _Clock()
    monkeypatch.setattr(modbus_link, "time", clock)
    line = _SlowLine(clock)
    link = ModbusLink(line, "modbus-tcp:scripted:1", timeout_s=TIMEOUT_S)
    link.timer.read_registers = lambda: _MIN_CHUNK  # the chunk size of a noisy line
    return link, line


def test_an_empty_window_costs_one_chunk_and_the_wait_ends_at_a_read_begun_after_the_deadline(monkeypatch):
    link, line = _scripted_link(monkeypatch)
    with pytest.raises(LinkError, match=f"no centroid frame within {TIMEOUT_S:g} s"):
        link.recv_frame()
    base, header = link.map.checked_block("window").read_span(0)  # the fixed registers and their check
    assert header < 119  # the whole head the link read at every poll before: 15 chunks
    # each poll reads the header alone, in chunks of _MIN_CHUNK registers: 2 exchanges (1.4 s on this line)
    assert {(a, c) for _, a, c in line.reads} == {(base, _MIN_CHUNK), (base + _MIN_CHUNK, header - _MIN_CHUNK)}
    polls = [t for t, address, _ in line.reads if address == base]
    # polls while the sensor had time (0 and 1.402 s), then one begun after the deadline (2.804 s) that ends it
    assert len(polls) == 3 and polls[-2] < TIMEOUT_S <= polls[-1]


def test_a_state_damaged_to_empty_is_read_again_not_taken_for_an_empty_window(monkeypatch):
    """Four reads of a window that holds the end of the stream come back with its state flipped to "no message",
    the last of them begun after the deadline: each fails the block check and is read again, and the fifth
    delivers the end of the stream."""
    link, line = _scripted_link(monkeypatch)
    link.set_streaming(True)  # the sensor has nothing to stream: its window holds the end of the stream
    line.reads.clear()
    started = line.clock.t
    line.damage_state = 4
    assert link.recv_frame() is None  # the end of the stream, not "no centroid frame within 2 s"
    window_reads = [t - started for t, address, _ in line.reads if address == link.map["window_state"].address]
    assert window_reads[3] >= TIMEOUT_S and len(window_reads) == 5
    assert link.stats.corrupt_frames == 4


def test_a_frame_whose_head_is_read_in_chunks_arrives_intact_on_the_real_client():
    with running_emulator("modbus", "--sim-frames", "5", "--no-estimator") as info:
        with open_link(info["link"], timeout_s=10.0) as link:
            link.timer.read_registers = lambda: _MIN_CHUNK
            link.set_streaming(True)
            frames = [link.recv_frame(10.0) for _ in range(4)]
            lost, corrupt = link.stats.lost_messages, link.stats.corrupt_frames
            link.set_streaming(False)
    counters = [f.frame for f in frames]
    assert counters == list(range(counters[0], counters[0] + 4))  # consecutive, each once
    assert all(f.n_stars > 0 and len(f.x_px) == f.n_stars for f in frames)
    assert (lost, corrupt) == (0, 0)  # every chunked head passed its block check
