"""The Modbus register map file: consistent, documented (the docs page is generated from it and up to date), and its
word order is the documented one, checked against raw register values and against pymodbus' own converter."""

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient  # outside authority for the word order (not project code)

from protocol import modbus_map as mm
from protocol.messages import ESTIMATE_FIELDS, MsgType, NakCode
from protocol.param_table import PARAM_FIELDS

ROOT = Path(__file__).resolve().parents[1]


def test_docs_page_is_generated_from_the_map_and_up_to_date():
    page = (ROOT / "docs" / "modbus_map.md").read_text()
    assert page == mm.render_markdown(mm.load_map()), "regenerate: python -m protocol.modbus_map > docs/modbus_map.md"
    for reg in mm.load_map().registers:
        assert f"`{reg.name}`" in page


def test_every_entry_has_the_interface_fields_and_no_two_share_a_register():
    doc = json.loads((ROOT / "protocol" / "modbus_map.json").read_text())
    for e in doc["registers"]:
        assert {"name", "table", "address", "type", "word_order", "units"} <= set(e)  # docs/modbus_map.md
    m = mm.parse_map(json.dumps(doc))  # parse_map refuses overlaps
    used = [a for r in m.table("input") for a in r.occupied()]
    assert len(used) == len(set(used))


def test_overlapping_entries_are_refused():
    doc = json.loads(mm.map_text())
    doc["registers"][1]["address"] = doc["registers"][0]["address"] + 1  # inside the first float32
    with pytest.raises(mm.MapError, match="share"):
        mm.parse_map(json.dumps(doc))


def test_map_covers_the_parameter_table_the_estimate_and_the_protocol_codes():
    m = mm.load_map()
    for prefix in ("stage", "active", "staged"):
        addrs = [m[f"{prefix}_{f}"].address for f in PARAM_FIELDS]
        assert addrs == list(range(addrs[0], addrs[0] + 2 * len(PARAM_FIELDS), 2))  # contiguous, table order
        assert all(m[f"{prefix}_{f}"].type == "float32" for f in PARAM_FIELDS)
    assert all(m[f"estimate_{f}"].type == "float32" for f in ESTIMATE_FIELDS)
    assert {c["name"]: c["code"] for c in m.nak_codes} == {c.name: int(c) for c in NakCode}
    for c in m.commands:
        assert MsgType[c["name"]] == c["code"]
    assert all(r.access == "r" for r in m.table("input"))


def test_float32_word_order_is_high_word_first_on_raw_registers():
    reg = mm.load_map()["active_focal_length_mm"]
    assert reg.word_order == "big"
    assert mm.to_registers(reg, 1.0) == [0x3F80, 0x0000]  # IEEE-754 1.0 = 0x3F800000
    assert mm.to_registers(reg, -2.5) == [0xC020, 0x0000]  # -2.5 = 0xC0200000
    assert mm.from_registers(reg, [0x4049, 0x0FDB]) == np.float32(np.pi)  # 0x40490FDB = float32(pi)
    int64 = mm.load_map()["window_t_us"]
    assert mm.to_registers(int64, 0x0102030405060708) == [0x0102, 0x0304, 0x0506, 0x0708]
    assert mm.from_registers(int64, [0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE]) == -2


def test_word_order_agrees_with_pymodbus_big_word_order():
    reg = mm.load_map()["stage_k1"]
    rng = np.random.default_rng(3)
    for v in rng.standard_normal(50) * 10.0 ** rng.integers(-12, 6, 50):
        ours = mm.to_registers(reg, float(v))
        theirs = ModbusTcpClient.convert_to_registers(float(v), ModbusTcpClient.DATATYPE.FLOAT32, word_order="big")
        assert ours == theirs
        back = ModbusTcpClient.convert_from_registers(ours, ModbusTcpClient.DATATYPE.FLOAT32, word_order="big")
        assert back == mm.from_registers(reg, ours) == np.float32(v)


def test_parameter_table_survives_registers_bit_for_bit():
    values = np.array(
        [25.0, 5.5, 511.25, 510.75, 1024, 1024, -3e-8, 1e-14, -2e-21, 1e-6, -1e-6, 0.0, -0.0], dtype="<f4"
    )
    table = values.tobytes()
    words = mm.registers_from_table(table)
    assert words[:2] == list(struct.unpack(">HH", struct.pack(">f", 25.0)))
    assert mm.table_from_registers(words) == table
    nan_payload = struct.pack("<I", 0x7FC00123)  # a NaN with a payload must not be canonicalised
    assert mm.table_from_registers(mm.registers_from_table(nan_payload * 13)) == nan_payload * 13


def test_stream_window_header_its_check_and_fifteen_stars_fit_one_read():
    m = mm.load_map()
    head = m["window_star_x_px"].address - m["window_state"].address
    stride = m["window_star_x_px"].stride
    assert m["window_crc32"].address == m["window_state"].address + head - 2  # the check ends the header
    assert head + 15 * stride <= mm.MAX_READ_REGISTERS
    x = m["window_star_x_px"]
    assert x.scale == 2.0**-10 and x.count == 255  # protocol.messages.CENTROID_LSB_PX, MAX_STARS


def test_signed_star_arrays_decode_vectorised_as_the_scalar_decoder_does():
    m = mm.load_map()
    x, mag = m["window_star_x_px"], m["window_star_mag"]
    base = m["window_state"].address
    words = [0] * (x.address - base + 3 * x.stride)
    for i, (xv, mv) in enumerate([(-1.5, -32.768), (2047.0009765625, 5.1), (0.0, 0.0)]):
        start = x.element_address(i) - base
        words[start : start + 2] = mm.to_registers(x, xv)
        start = mag.element_address(i) - base
        words[start : start + 1] = mm.to_registers(mag, mv)
    raw_x = mm.array_raw(np.array(words), x, 3, base)
    raw_mag = mm.array_raw(np.array(words), mag, 3, base)
    assert list(raw_x * 2.0**-10) == [-1.5, 2047.0009765625, 0.0]
    assert list(raw_mag) == [-32768, 5100, 0]
