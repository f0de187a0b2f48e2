"""The generated COSMOS Modbus/TCP target against the emulated sensor's Modbus server, through openc3's own code:
the interface built from the generated plugin.txt by COSMOS's InterfaceModel (its TCP/IP client interface with its
LENGTH protocol framing MBAP), every command built by COSMOS's Commands, every reply identified by COSMOS's
Telemetry. Every register openc3 decodes is compared with hostlink's decoding of the same reply's registers
(``protocol.modbus_map``), every block's check register verified, and the stream's stars compared with the session
the sensor replays. The campaign runs the map's every command (the safe upload, the stream) and reads every block."""

from __future__ import annotations

import math
import os
import struct
import zlib

import numpy as np
import pytest
from emulator_fixtures import running_emulator

# openc3 outside a COSMOS installation: its logger prints, and publishes nothing to COSMOS's Redis (as openc3's own
# command-line tool sets it)
os.environ.setdefault("OPENC3_NO_STORE", "1")
pytest.importorskip("openc3", reason="openc3 is the [cosmos] test extra (pyproject.toml), needs numpy >= 2")

from ground_cosmos import build_interface  # noqa: E402

from hostlink.files.session import read_session, write_session  # noqa: E402
from hostlink.portkit import ground_modbus  # noqa: E402
from hostlink.portkit.export_ground import COSMOS_PLUGIN, MODBUS_CMD, MODBUS_TLM, write_ground  # noqa: E402
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate  # noqa: E402
from protocol import modbus_map as mm  # noqa: E402
from protocol.param_table import PARAM_FIELDS, TABLE_BYTES  # noqa: E402

TARGET = ground_modbus.TARGET
FRAMES = 12
WINDOW_FRAME, WINDOW_END = 1, 2
#: MBAP header (7 bytes), function code and byte count: where a read reply's registers start.
REGISTERS_AT = 9


class ModbusCampaign:
    def __init__(self, config, interface) -> None:  # noqa: ANN001 - openc3 objects
        from openc3.packets.commands import Commands
        from openc3.packets.telemetry import Telemetry

        self.tlm, self.cmds, self.interface = Telemetry(config, None), Commands(config, None), interface
        self.map = mm.load_map()
        self.blocks = {rb.name: rb for rb in ground_modbus.read_blocks(self.map)}
        self.problems: list[str] = []
        self.values_compared = 0
        self.packets: set[str] = set()
        self.commands: set[str] = set()

    def exchange(self, command: str, **params):  # noqa: ANN201 - the identified reply
        self.interface.write(self.cmds.build_cmd(TARGET, command, params))
        self.commands.add(command)
        packet = self.tlm.identify_and_define_packet(self.interface.read(), [TARGET])
        assert packet is not None, f"no identifiable reply to {command}"
        self.packets.add(packet.packet_name)
        return packet

    def read(self, name: str):  # noqa: ANN201 - (the identified reply, its registers)
        """READ_<name>: the reply, compared register by register with protocol.modbus_map's decoding."""
        packet = self.exchange(f"READ_{name}")
        assert packet.packet_name == name
        rb = self.blocks[name]
        data = bytes(packet.buffer_no_copy())
        words = list(struct.unpack(f">{rb.count}H", data[REGISTERS_AT : REGISTERS_AT + 2 * rb.count]))
        if packet.read("BYTE_COUNT") != 2 * rb.count or len(data) != REGISTERS_AT + 2 * rb.count:
            self.problems.append(f"{name}: {len(data)} bytes")
        for reg, index in rb.entries:
            want = mm.get(words, reg, index or 0, base=rb.address)
            got = packet.read(ground_modbus.item_name(reg, index))
            same = (isinstance(want, float) and math.isnan(want) and math.isnan(got)) or got == want
            if not same:
                self.problems.append(f"{name}.{ground_modbus.item_name(reg, index)}: openc3 {got!r}, hostlink {want!r}")
            self.values_compared += 1
        return packet, words

    def write(self, name: str, **params) -> None:
        reply = self.exchange(f"WRITE_{name}", **params)
        assert reply.packet_name == "WRITE_RESPONSE" and reply.read("FUNCTION_CODE") == ground_modbus.FC_WRITE_MULTIPLE

    def command(self, code: str, **registers):  # noqa: ANN201 - the RESULT reply
        for name, value in registers.items():
            self.write(name, **{name: value})
        self.write("COMMAND", COMMAND=code)
        result, words = self.read("RESULT")
        assert mm.block_intact(self.map.checked_block("result"), words, self.blocks["RESULT"].address)
        assert result.read("RESULT_COMMAND") == self.map.command_code(code)
        return result


def test_openc3_runs_the_modbus_map_against_the_emulated_sensor(tmp_path):
    from openc3.packets.packet_config import PacketConfig

    write_ground(tmp_path / "ground")
    config = PacketConfig()
    for name in (MODBUS_CMD, MODBUS_TLM):
        config.process_file(str(tmp_path / "ground" / name), TARGET)
    assert config.warnings == []
    session = tmp_path / "session.csv"
    sim = simulate(SimConfig(camera=seed004_camera(), frames=FRAMES, noise_px=0.05, seed=33, false_star_fraction=0.1))
    write_session(session, sim.session)
    source = read_session(session)
    with running_emulator("modbus", "--replay", str(session)) as info:
        plugin = tmp_path / "ground" / COSMOS_PLUGIN
        variables = {"modbus_host": "127.0.0.1", "modbus_port": info["port"]}
        interface = build_interface(plugin, ground_modbus.INTERFACE, variables)
        assert [type(p).__name__ for p in interface.read_protocols] == ["LengthProtocol"]
        interface.connect()
        try:
            c = ModbusCampaign(config, interface)
            status, words = c.read("STATUS")
            assert mm.block_intact(c.map.checked_block("status"), words, c.blocks["STATUS"].address)
            assert status.read("STATUS_STREAMING") == 0
            active, words = c.read("ACTIVE")
            assert mm.block_intact(c.map.checked_block("active"), words, c.blocks["ACTIVE"].address)
            values = {f: active.read(f"ACTIVE_{f.upper()}") for f in PARAM_FIELDS}
            table = mm.table_from_registers(words[6 : 6 + 2 * len(PARAM_FIELDS)])
            assert zlib.crc32(table) == active.read("ACTIVE_CRC32") == status.read("STATUS_ACTIVE_CRC32")
            generation = active.read("ACTIVE_GENERATION")
            estimate, _ = c.read("ESTIMATE")
            assert estimate.read("ESTIMATE_NAK_CODE") == 7  # NO_ESTIMATE: nothing streamed yet
            # the safe upload through the mailbox, every write built by openc3: the active set staged again
            begin = c.command("STAGE_BEGIN", COMMAND_ARG=TABLE_BYTES)
            assert begin.read("RESULT_STATUS") == 1
            nonce = begin.read("RESULT_VALUE")
            c.write("STAGE_TABLE", **{f"STAGE_{f.upper()}": v for f, v in values.items()})
            chunk = c.command("STAGE_CHUNK", COMMAND_ARG=0, COMMAND_LENGTH=TABLE_BYTES)
            assert chunk.read("RESULT_STATUS") == 1, chunk.read("RESULT_TEXT")
            assert c.command("STAGE_VERIFY", COMMAND_CRC32=zlib.crc32(table)).read("RESULT_STATUS") == 1
            staged, words = c.read("STAGED")
            assert mm.block_intact(c.map.checked_block("staged"), words, c.blocks["STAGED"].address)
            assert mm.table_from_registers(words[4 : 4 + 2 * len(PARAM_FIELDS)]) == table
            commit = c.command(
                "COMMIT", COMMAND_CRC32=zlib.crc32(table), COMMAND_NONCE=nonce, COMMAND_EXPECTED_GENERATION=generation
            )
            assert (commit.read("RESULT_STATUS"), commit.read("RESULT_VALUE")) == (1, generation + 1)
            # the stream: every frame read (head and star pages), checked, compared with the session, released
            assert c.command("STREAM_CONTROL", COMMAND_ARG=1).read("RESULT_STATUS") == 1
            window = c.map.checked_block("window")
            frames = 0
            while True:
                head, words = c.read("WINDOW")
                state, n = head.read("WINDOW_STATE"), head.read("WINDOW_N_STARS")
                if state not in (WINDOW_FRAME, WINDOW_END):
                    continue
                pages = [rb.name for rb in c.blocks.values() if rb.name.startswith("WINDOW_STARS_")]
                in_head = ground_modbus._window_stars_in_head(window)
                per_page = mm.MAX_READ_REGISTERS // window.stars_from.stride
                for page in pages[: max(0, -(-(n - in_head) // per_page))]:
                    words += c.read(page)[1]
                assert mm.block_intact(window, words[: window.read_span(n)[1]], c.blocks["WINDOW"].address)
                seq = head.read("WINDOW_SEQ")
                if state == WINDOW_END:
                    break
                rows = source.frame == head.read("WINDOW_FRAME")
                assert n == int(np.count_nonzero(rows))
                assert np.array_equal(
                    mm.array_raw(np.asarray(words), c.map["window_star_id"], n, 1000), source.star_id[rows]
                )
                x = mm.array_raw(np.asarray(words), c.map["window_star_x_px"], n, 1000)
                assert np.array_equal(x, np.rint(source.x_px[rows] * 1024).astype(np.int64))
                frames += 1
                c.write("STREAM_ACK_SEQ", STREAM_ACK_SEQ=seq)
            assert frames == FRAMES
            estimate, _ = c.read("ESTIMATE")
            assert estimate.read("ESTIMATE_NAK_CODE") == 0 and estimate.read("ESTIMATE_UPDATES") > 0
            assert c.command("STREAM_CONTROL", COMMAND_ARG=0).read("RESULT_STATUS") == 1
        finally:
            interface.disconnect()
    assert c.problems == []
    assert c.values_compared > FRAMES * 14 * 2
    assert {"RESULT", "STATUS", "ACTIVE", "STAGED", "ESTIMATE", "WINDOW", "WINDOW_STARS_1"} <= c.packets
    assert {f"WRITE_{n}" for n in ("COMMAND", "COMMAND_ARG", "COMMAND_LENGTH", "COMMAND_CRC32", "STAGE_TABLE")} <= (
        c.commands
    )
