"""The generated COSMOS target driving the emulated sensor over a pty, through openc3's own code: the interface is
built from the generated plugin.txt by COSMOS's InterfaceModel (its SerialInterface with its COBS and CRC
protocols), every packet it reads is identified by COSMOS's Telemetry against the generated definitions, and every
command is built by COSMOS's Commands. The bytes the interface read are tapped and decoded independently by hostlink
(protocol.framing + protocol.messages): every packet must be the message hostlink decodes there, field by field.

The campaign sends every command type the sensor takes (status, the six-step safe upload, the stream, the estimate),
so the sensor answers with every reply and stream type: all 16 message types cross the link."""

from __future__ import annotations

import collections
import os
import threading
import zlib
from pathlib import Path

import pytest
from emulator_fixtures import running_emulator

# openc3 outside a COSMOS installation: its logger prints, and publishes nothing to COSMOS's Redis (as openc3's own
# command-line tool sets it)
os.environ.setdefault("OPENC3_NO_STORE", "1")
pytest.importorskip("openc3", reason="openc3 is the [cosmos] test extra (pyproject.toml), needs numpy >= 2")

from ground_cosmos import build_interface, load_target, mismatches  # noqa: E402

from hostlink.files.session import write_session  # noqa: E402
from hostlink.portkit.export_ground import COSMOS_PLUGIN, SERIAL_INTERFACE, TARGET  # noqa: E402
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate  # noqa: E402
from protocol.framing import FrameSplitter, decode_frame  # noqa: E402
from protocol.messages import MESSAGES, TABLE_BYTES, decode  # noqa: E402

#: Frames of the replayed session in the normal run (the acceptance figure, 1000 frames, is the slow test's).
FRAMES = 120
#: A stuck read (a sensor that stopped answering) ends the campaign after this long [s] instead of hanging the suite.
WATCHDOG_S = 300.0
#: The line rate of the campaign [bit/s]: fast, so that 1000 frames take seconds (the pty has no physical limit).
BAUD = 4_000_000


class Campaign:
    """openc3 on one side of the line, hostlink's decoder on a tap of the same bytes."""

    def __init__(self, config, interface) -> None:  # noqa: ANN001 - openc3 objects
        from openc3.packets.commands import Commands
        from openc3.packets.telemetry import Telemetry

        self.tlm, self.cmds, self.interface = Telemetry(config, None), Commands(config, None), interface
        self.splitter, self.hostlink_queue = FrameSplitter(), collections.deque()
        self.count: collections.Counter = collections.Counter()
        self.problems: list[str] = []
        self.items_compared = 0
        read = interface.read_interface

        def tapped_read():  # the bytes the interface read, as they came off the line
            data, extra = read()
            if data:
                for raw in self.splitter.feed(bytes(data)):
                    frame = decode_frame(raw)
                    self.hostlink_queue.append((frame.seq, decode(frame.payload)))
            return data, extra

        interface.read_interface = tapped_read

    def send(self, name: str, **params):  # noqa: ANN201 - the answering openc3 packet
        """Build command ``name`` with openc3, write it, read until the reply with its tag; compare all read."""
        command = self.cmds.build_cmd(TARGET, name, params)
        self.interface.write(command)
        self.count[name] += 1
        while True:
            packet = self.receive()
            if packet.packet_name in ("ACK", "NAK", "TELEMETRY", "PARAM_TABLE", "ESTIMATE"):
                if packet.read("TAG") == params["TAG"]:
                    return packet

    def receive(self):  # noqa: ANN201 - an identified openc3 packet
        packet = self.tlm.identify_and_define_packet(self.interface.read(), [TARGET])
        assert packet is not None, "a packet openc3 could not identify"
        seq, msg = self.hostlink_queue.popleft()
        self.problems += mismatches(packet, msg, seq)
        self.items_compared += sum(1 for i in packet.sorted_items if i.data_type != "DERIVED")
        self.count[packet.packet_name] += 1
        return packet


def run_campaign(tmp_path: Path, frames: int) -> Campaign:
    config = load_target(tmp_path / "ground")
    session = tmp_path / "session.csv"
    sim = simulate(SimConfig(camera=seed004_camera(), frames=frames, noise_px=0.05, seed=32, false_star_fraction=0.1))
    write_session(session, sim.session)
    with running_emulator("serial", "--replay", str(session), "--baud", str(BAUD)) as info:
        port, baud = info["link"].removeprefix("serial:").split("@")
        plugin = tmp_path / "ground" / COSMOS_PLUGIN
        interface = build_interface(plugin, SERIAL_INTERFACE, {"port": port, "baud": baud})
        assert [type(p).__name__ for p in interface.read_protocols] == ["CobsProtocol", "CrcProtocol"]
        interface.connect()
        watchdog = threading.Timer(WATCHDOG_S, interface.disconnect)
        watchdog.start()
        try:
            c = Campaign(config, interface)
            status = c.send("GET_STATUS", TAG=1)
            assert status.packet_name == "TELEMETRY" and status.read("STREAMING") == "FALSE"
            active = c.send("READ_ACTIVE", TAG=2)
            assert active.packet_name == "PARAM_TABLE" and active.read("BANK") == "ACTIVE"
            generation, table = active.read("GENERATION"), bytes(active.read("TABLE"))
            assert c.send("READ_ESTIMATE", TAG=3).read("CODE") == "NO_ESTIMATE"
            assert c.send("READ_STAGED", TAG=4).read("CODE") == "NOT_STAGED"
            # the safe upload, every step built by openc3: the active set staged again, verified, read back, committed
            nonce = c.send("STAGE_BEGIN", TAG=5, LENGTH=TABLE_BYTES).read("VALUE")
            half = TABLE_BYTES // 2
            assert c.send("STAGE_CHUNK", TAG=6, OFFSET=0, DATA=table[:half]).packet_name == "ACK"
            assert c.send("STAGE_CHUNK", TAG=7, OFFSET=half, DATA=table[half:]).packet_name == "ACK"
            assert c.send("STAGE_VERIFY", TAG=8, CRC32=zlib.crc32(table)).packet_name == "ACK"
            staged = c.send("READ_STAGED", TAG=9)
            assert staged.read("BANK") == "STAGED" and bytes(staged.read("TABLE")) == table
            committed = c.send("COMMIT", TAG=10, CRC32=zlib.crc32(table), NONCE=nonce, EXPECTED_GENERATION=generation)
            assert committed.packet_name == "ACK" and committed.read("VALUE") == generation + 1
            # the stream: started by openc3, read to its end
            assert c.send("STREAM_CONTROL", TAG=11, ENABLE="TRUE").packet_name == "ACK"
            while c.receive().packet_name != "END_OF_STREAM":
                pass
            assert c.send("READ_ESTIMATE", TAG=12).packet_name == "ESTIMATE"
            assert c.send("STREAM_CONTROL", TAG=13, ENABLE="FALSE").packet_name == "ACK"
        finally:
            watchdog.cancel()
            interface.disconnect()
    return c


def _check(c: Campaign, frames: int) -> None:
    assert c.problems == []
    assert c.count["CENTROID_FRAME"] == frames
    assert set(c.count) == {s.name for s in MESSAGES}, "every message type crossed the link"
    assert not c.hostlink_queue, "hostlink decoded a message openc3 did not deliver"


def test_openc3_drives_the_emulated_sensor_and_decodes_every_packet_as_hostlink(tmp_path):
    c = run_campaign(tmp_path, FRAMES)
    _check(c, FRAMES)


@pytest.mark.slow
def test_openc3_round_trip_over_a_1000_frame_stream(tmp_path):
    c = run_campaign(tmp_path, 1000)
    _check(c, 1000)
    assert c.items_compared > 1000 * 1024
