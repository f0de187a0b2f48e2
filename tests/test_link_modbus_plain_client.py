"""A plain pymodbus client, with no project code (only protocol/modbus_map.json read as data), reads and writes the
staged parameters, stages, verifies and commits them, and reads the active set back, by the map alone; the float
word order is checked on raw registers. The emulator runs as a separate process (tests/emulator_fixtures.py starts
``hostlink emulate``; nothing of the project is imported here)."""

import json
import struct
import zlib
from pathlib import Path

import pytest
from emulator_fixtures import running_emulator
from pymodbus.client import ModbusTcpClient
from pymodbus.framer import FramerType

MAP = json.loads((Path(__file__).resolve().parents[1] / "protocol" / "modbus_map.json").read_text())
REG = {r["name"]: r for r in MAP["registers"]}
CMD = {c["name"]: c["code"] for c in MAP["commands"]}
FIELDS = [
    r["name"][len("stage_") :]
    for r in sorted(MAP["registers"], key=lambda r: r["address"])
    if r["name"].startswith("stage_")
]
# a camera within the emulator's detector (its factory set is seed 004's 1024 x 1024 camera)
CAMERA = {
    "focal_length_mm": 69.75,
    "pixel_pitch_um": 12.0,
    "principal_point_x_px": 512.3,
    "principal_point_y_px": 509.8,
    "image_width_px": 1024.0,
    "image_height_px": 1024.0,
    "k1": -3.1e-9,
    "k2": 1.0e-16,
    "k3": 0.0,
    "p1": 2.0e-7,
    "p2": -1.0e-7,
    "s1": 0.0,
    "s2": 0.0,
    # the 1-sigma prior the sensor's estimator restarts from (0 = unknown: cold-start prior)
    "sigma_focal_length_mm": 7e-4,
    "sigma_principal_point_x_px": 1.3,
    "sigma_principal_point_y_px": 1.29,
    "sigma_k1": 1.4e-10,
    "sigma_k2": 5.8e-16,
    "sigma_k3": 0.0,
    "sigma_p1": 2.2e-8,
    "sigma_p2": 2.1e-8,
    "sigma_s1": 2.0e-8,
    "sigma_s2": 2.0e-8,
}


def f32_words(value):
    """float32 -> two registers, high word first: the map's documented word order, done by hand."""
    assert MAP["word_order"] == "big"
    return list(struct.unpack(">HH", struct.pack(">f", value)))


def u32_words(value):
    return [(value >> 16) & 0xFFFF, value & 0xFFFF]


def words_f32(words):
    return struct.unpack(">f", struct.pack(">HH", *words))[0]


def words_u32(words):
    return (words[0] << 16) | words[1]


def run_command(client, unit, name, arg=0, length=0, crc=0):
    base = REG["command_arg"]["address"]
    block = [0] * (REG["command"]["address"] - base + 1)
    block[REG["command_arg"]["address"] - base] = arg
    block[REG["command_length"]["address"] - base] = length
    block[REG["command_crc32"]["address"] - base : REG["command_crc32"]["address"] - base + 2] = u32_words(crc)
    block[REG["command"]["address"] - base] = CMD[name]
    assert not client.write_registers(base, block, device_id=unit).isError()
    res = client.read_input_registers(REG["result_command"]["address"], count=8, device_id=unit).registers
    text_reg = REG["result_text"]
    text_words = client.read_input_registers(
        text_reg["address"], count=text_reg["length_bytes"] // 2, device_id=unit
    ).registers
    text = struct.pack(f">{len(text_words)}H", *text_words).rstrip(b"\0").decode()
    status_at = REG["result_status"]["address"] - REG["result_command"]["address"]
    value_at = REG["result_value"]["address"] - REG["result_command"]["address"]
    return res[status_at], words_u32(res[value_at : value_at + 2]), text


def write_session(client, unit, nonce, expected_generation):
    """COMMIT's session registers (outside the command block): STAGE_BEGIN's nonce and the generation it replaces."""
    base = REG["command_nonce"]["address"]
    words = [0] * (REG["command_expected_generation"]["address"] + 2 - base)
    words[0:2] = u32_words(nonce)
    at = REG["command_expected_generation"]["address"] - base
    words[at : at + 2] = u32_words(expected_generation)
    assert not client.write_registers(base, words, device_id=unit).isError()


@pytest.mark.parametrize("framing", ["tcp", "rtu"])
def test_plain_pymodbus_client_uploads_and_reads_back_by_the_map(framing):
    with running_emulator("modbus", "--sim-frames", "20") as info:
        unit = info["unit"]
        port = info["port"] if framing == "tcp" else info["rtu_port"]
        client = ModbusTcpClient(
            "127.0.0.1", port=port, framer=FramerType.SOCKET if framing == "tcp" else FramerType.RTU, timeout=3
        )
        assert client.connect()
        try:
            stage = REG[f"stage_{FIELDS[0]}"]["address"]
            words = [w for f in FIELDS for w in f32_words(CAMERA[f])]
            assert not client.write_registers(stage, words, device_id=unit).isError()
            back = client.read_holding_registers(stage, count=len(words), device_id=unit).registers
            assert back == words  # the staging mailbox holds exactly what was written

            table = struct.pack(f"<{len(FIELDS)}f", *(CAMERA[f] for f in FIELDS))
            crc = zlib.crc32(table)
            status, nonce, _ = run_command(client, unit, "STAGE_BEGIN", arg=len(table))
            assert status == 1 and nonce > 0  # the staging session's nonce
            assert run_command(client, unit, "STAGE_CHUNK", arg=0, length=len(table))[0] == 1
            assert run_command(client, unit, "STAGE_VERIFY", crc=crc)[0] == 1
            write_session(client, unit, nonce - 1, 1)  # not this session: refused, nothing switched
            assert run_command(client, unit, "COMMIT", crc=crc)[0] == 2
            write_session(client, unit, nonce, 1)
            status, generation, _ = run_command(client, unit, "COMMIT", crc=crc)
            assert status == 1 and generation == 2

            active = REG[f"active_{FIELDS[0]}"]["address"]
            raw = client.read_input_registers(active, count=2 * len(FIELDS), device_id=unit).registers
            for i, f in enumerate(FIELDS):
                # equal to float32 of the file value, bit for bit, on the raw registers
                assert raw[2 * i : 2 * i + 2] == f32_words(CAMERA[f])
                assert words_f32(raw[2 * i : 2 * i + 2]) == struct.unpack(">f", struct.pack(">f", CAMERA[f]))[0]
            head = client.read_input_registers(REG["active_generation"]["address"], count=4, device_id=unit).registers
            assert words_u32(head[:2]) == 2 and words_u32(head[2:]) == crc
            # the word order, by hand: focal length 69.75 = 0x428B8000 -> [0x428B, 0x8000]
            assert raw[:2] == [0x428B, 0x8000]
        finally:
            client.close()


def test_plain_client_sees_a_refusal_with_its_reason():
    with running_emulator("modbus", "--sim-frames", "20") as info:
        unit = info["unit"]
        client = ModbusTcpClient("127.0.0.1", port=info["port"], timeout=3)
        assert client.connect()
        try:
            bad = dict(CAMERA, principal_point_x_px=5000.0)
            words = [w for f in FIELDS for w in f32_words(bad[f])]
            client.write_registers(REG[f"stage_{FIELDS[0]}"]["address"], words, device_id=unit)
            table = struct.pack(f"<{len(FIELDS)}f", *(bad[f] for f in FIELDS))
            _, nonce, _ = run_command(client, unit, "STAGE_BEGIN", arg=len(table))
            write_session(client, unit, nonce, 1)  # the right session: the refusal below is the set's own
            run_command(client, unit, "STAGE_CHUNK", arg=0, length=len(table))
            status, _, text = run_command(client, unit, "STAGE_VERIFY", crc=zlib.crc32(table))
            code = client.read_input_registers(REG["result_code"]["address"], count=1, device_id=unit).registers[0]
            assert status == 2 and {c["code"]: c["name"] for c in MAP["nak_codes"]}[code] == "INVALID_PARAMS"
            assert "principal_point_px[0]" in text and "5000" in text
            status, _, _ = run_command(client, unit, "COMMIT", crc=zlib.crc32(table))
            assert status == 2  # never committed
            gen = client.read_input_registers(REG["active_generation"]["address"], count=2, device_id=unit).registers
            assert words_u32(gen) == 1
        finally:
            client.close()
