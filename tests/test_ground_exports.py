"""The ground-system exports (hostlink export-ground) against the protocol table, read by the real clients: the COSMOS
target loaded by openc3's own parser (PacketConfig), every message type decoded and built by openc3 exactly as
hostlink decodes and encodes it, and the XTCE document (yamcs-pymdb) checked field by field against openc3's own
XTCE export of the COSMOS target."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

# openc3 outside a COSMOS installation: its logger prints, and publishes nothing to COSMOS's Redis (as openc3's own
# command-line tool sets it)
os.environ.setdefault("OPENC3_NO_STORE", "1")
pytest.importorskip("openc3", reason="openc3 is the [cosmos] test extra (pyproject.toml), needs numpy >= 2")

from ground_cosmos import expected_items, expected_values, load_target, mismatches  # noqa: E402

from hostlink.portkit import export_ground  # noqa: E402
from protocol import messages  # noqa: E402
from protocol.messages import (  # noqa: E402
    MESSAGES,
    Ack,
    CentroidFrame,
    Commit,
    EndOfStream,
    Estimate,
    GetStatus,
    MessageSpec,
    Nak,
    ParamTable,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    Telemetry,
    WireField,
    encode,
    spec_of,
)
from protocol.param_table import PARAM_FIELDS, table_from_mapping  # noqa: E402

TARGET = export_ground.TARGET
XTCE_NS = {"x": "http://www.omg.org/spec/XTCE/20180204"}


def sample_messages() -> list:
    """One message of every type, with values that exercise every field (signs, NaN, absent magnitudes, UTF-8)."""
    rng = np.random.default_rng(32)
    n = 7
    frame = CentroidFrame(
        frame=4_000_000_001,
        t_us=1_767_225_600_123_456,
        star_id=rng.integers(0, 120_000, n).astype(np.uint32),
        x_px=np.round(rng.uniform(-10, 1030, n) * 1024) / 1024,
        y_px=np.round(rng.uniform(-10, 1030, n) * 1024) / 1024,
        mag=np.array([5.1, np.nan, -1.46, 12.345, 0.0, np.nan, 32.767]),
    )
    table = {f: float(v) for f, v in zip(PARAM_FIELDS, rng.normal(0, 1e-3, len(PARAM_FIELDS)), strict=True)}
    table |= {"focal_length_mm": 70.2262, "image_width_px": 1024.0, "sigma_k1": math.nan}
    return [
        GetStatus(tag=1),
        StreamControl(tag=2, enable=False),
        StageBegin(tag=3, length=92),
        StageChunk(tag=4, offset=46, data=bytes(range(0, 255, 5))),
        StageVerify(tag=5, crc32=0xDEADBEEF),
        ReadStaged(tag=6),
        Commit(tag=7, crc32=0x01020304, nonce=0xFFFFFFFE, expected_generation=12),
        ReadActive(tag=8),
        ReadEstimate(tag=9),
        Ack(tag=65535, command=7, value=13),
        Nak(tag=10, command=5, code=10, text="focal_length_mm: 1e9 is not plausible (µ)"),
        Telemetry(tag=11, streaming=True, stage_state=2, active_generation=3, active_crc32=4, frames_processed=5),
        ParamTable(tag=12, bank=0, generation=0, crc32=99, table=table_from_mapping(table)),
        Estimate(
            tag=13,
            status=1,
            estimated_mask=0x3FF,
            base_generation=2,
            n_updates=1000,
            last_frame=999,
            values=tuple(float(np.float32(v)) for v in rng.normal(0, 1, 10)),
            sigma=(math.nan,) * 3 + tuple(float(np.float32(v)) for v in rng.uniform(0, 1, 7)),
        ),
        frame,
        CentroidFrame(frame=1, t_us=-5),
        EndOfStream(frames_sent=1000),
    ]


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    directory = tmp_path_factory.mktemp("ground")
    return directory, load_target(directory)


def target_differences(config, table: tuple[MessageSpec, ...]) -> list[str]:
    """Every way the loaded COSMOS target differs from the protocol table (item names, order, sizes, data types,
    units, descriptions, states); [] when it carries every field of every message."""
    out = []
    for spec in table:
        kind = config.commands if spec.is_command else config.telemetry
        packet = kind[TARGET].get(spec.name)
        if packet is None:
            out.append(f"{spec.name}: no packet")
            continue
        # COSMOS adds its own time items; the parameter table's values are views laid over its bytes (OVERLAP)
        wire = [i for i in packet.sorted_items if i.data_type != "DERIVED" and not i.overlap]
        got = [(i.name, i.bit_size if not i.variable_bit_size else 0, i.data_type) for i in wire]
        want = list(expected_items(spec))
        if got != want:
            missing = sorted({w[0] for w in want} - {g[0] for g in got})
            out.append(f"{spec.name}: items differ (missing {missing[:5]})" if missing else f"{spec.name}: items")
            continue
        for f in spec.fields:
            members = f.record if f.fmt == "record" else (f,)
            for m in members:
                name = m.name.upper() if f.fmt != "record" else f"STAR_000_{m.name.upper().replace('STAR_', '')}"
                item = packet.get_item(name)
                if m.unit and item.units != m.unit:
                    out.append(f"{spec.name}.{name}: unit {item.units!r}, protocol {m.unit!r}")
                if not item.description:
                    out.append(f"{spec.name}.{name}: no description")
                if m.fmt == "?" and item.states != {"FALSE": 0, "TRUE": 1}:
                    out.append(f"{spec.name}.{name}: states {item.states}")
    return out


def test_the_cosmos_target_carries_every_field_of_the_protocol(target):
    _, config = target
    assert config.warnings == []
    assert target_differences(config, MESSAGES) == []
    assert set(config.commands[TARGET]) == {s.name for s in MESSAGES if s.is_command}
    assert set(config.telemetry[TARGET]) == {s.name for s in MESSAGES if not s.is_command}
    # enumerations: the states are the protocol's IntEnum members, on the fields whose description names them
    nak = config.telemetry[TARGET]["NAK"]
    assert nak.get_item("CODE").states == {c.name: int(c) for c in messages.NakCode}
    assert nak.get_item("COMMAND").states == {c.name: int(c) for c in messages.MsgType}
    assert config.telemetry[TARGET]["TELEMETRY"].get_item("STAGE_STATE").states == {
        c.name: int(c) for c in messages.StageState
    }


def test_a_field_added_to_the_protocol_and_not_to_the_exports_fails(target, tmp_path, monkeypatch):
    _, config = target
    frame = next(s for s in MESSAGES if s.name == "TELEMETRY")
    extra = WireField("temperature_mk", "H", unit="mK", doc="detector temperature")
    grown = tuple(dataclasses.replace(s, fields=(*s.fields, extra)) if s is frame else s for s in MESSAGES)
    # the exports made before the field was added miss it: the check says so
    assert target_differences(config, grown) == ["TELEMETRY: items differ (missing ['TEMPERATURE_MK'])"]
    # the generator reads the table: regenerated, the exports carry it (COSMOS and XTCE)
    monkeypatch.setattr(export_ground, "MESSAGES", grown)
    regenerated = load_target(tmp_path)
    assert target_differences(regenerated, grown) == []
    assert regenerated.telemetry[TARGET]["TELEMETRY"].get_item("TEMPERATURE_MK").units == "mK"
    xtce = ET.parse(tmp_path / export_ground.XTCE_FILE).getroot()
    assert xtce.find(".//x:ParameterSet/x:Parameter[@name='TELEMETRY_TEMPERATURE_MK']", XTCE_NS) is not None


def test_openc3_decodes_every_message_type_as_hostlink_does(target):
    from openc3.packets.commands import Commands
    from openc3.packets.telemetry import Telemetry as Tlm

    _, config = target
    tlm, cmds = Tlm(config, None), Commands(config, None)
    seen = set()
    for k, msg in enumerate(sample_messages()):
        data = (1000 + k).to_bytes(2, "little") + encode(msg)
        spec = spec_of(msg)
        found = (cmds if spec.is_command else tlm).identify(data, [TARGET])
        assert found is not None, spec.name
        packet = found.clone()
        packet.buffer = data
        assert mismatches(packet, msg, 1000 + k) == []
        seen.add(spec.name)
    assert seen == {s.name for s in MESSAGES}


def test_commands_built_by_openc3_are_byte_identical_to_hostlinks(target):
    from openc3.packets.commands import Commands

    _, config = target
    cmds = Commands(config, None)
    commands = [m for m in sample_messages() if spec_of(m).is_command]
    assert {spec_of(m).name for m in commands} == {s.name for s in MESSAGES if s.is_command}
    for msg in commands:
        spec = spec_of(msg)
        params = {k: v for k, v in expected_values(msg, 0).items() if k not in ("TYPE", "SEQ", "N_BYTES")}
        params = {k: ("TRUE" if v else "FALSE") if isinstance(v, bool) else v for k, v in params.items()}
        built = cmds.build_cmd(TARGET, spec.name, params)
        assert bytes(built.buffer) == b"\x00\x00" + encode(msg), spec.name


def _x(tag: str) -> str:
    return f"{{{XTCE_NS['x']}}}{tag}"


def _types(root: ET.Element, kind: str) -> dict[str, ET.Element]:
    return {e.get("name"): e for e in root.find(f".//x:{kind}TypeSet", XTCE_NS)}


def _type_of(types: dict[str, ET.Element], name: str, variable: bool) -> tuple:
    """A type as compared across the two documents: (kind, encoding element, size in bits, encoding, byte order,
    calibrator terms, unit, enumeration), an array as ("Array", length, its element's description). ``variable``:
    the COSMOS item is sized by a length item (openc3's exporter writes its COSMOS bit size, 0; ours a leading size)."""
    el = types[name]
    kind = el.tag.split("}")[1].replace("Parameter", "").replace("Argument", "").replace("Type", "")
    if kind == "Array":
        end = int(el.find(".//x:EndingIndex/x:FixedValue", XTCE_NS).text)
        return ("Array", end + 1, _type_of(types, el.get("arrayTypeRef"), False))
    enc = next(c for c in el if c.tag.endswith("DataEncoding"))
    unit = el.find("x:UnitSet/x:Unit", XTCE_NS)
    terms = tuple((float(t.get("coefficient")), int(t.get("exponent"))) for t in el.iter(_x("Term")))
    enums = tuple((int(e.get("value")), e.get("label")) for e in el.iter(_x("Enumeration")))
    if kind in ("String", "Binary"):
        size = "variable" if variable else next(v.text for v in enc.iter(_x("FixedValue")))
    else:
        size = enc.get("sizeInBits")
    order = enc.get("byteOrder") or ("mostSignificantByteFirst" if kind not in ("String", "Binary") else None)
    return (
        kind,
        enc.tag.split("}")[1],
        size,
        enc.get("encoding"),
        order,
        terms,
        unit.text if unit is not None else None,
        enums,
    )


def _condition(el: ET.Element) -> tuple[str, str, int]:
    cond = el.find(".//x:Condition", XTCE_NS)
    ref = cond.find("x:ParameterInstanceRef", XTCE_NS).get("parameterRef")
    return ref, cond.find("x:ComparisonOperator", XTCE_NS).text, int(cond.find("x:Value", XTCE_NS).text)


def _length_items(packet) -> set[str]:  # noqa: ANN001 - openc3 Packet
    """Items the XTCE does not carry as parameters: length items (a leading size there) and the parameter table's
    values (views over its bytes in COSMOS; the XTCE keeps the bytes)."""
    lengths = {i.variable_bit_size["length_item_name"] for i in packet.sorted_items if i.variable_bit_size}
    return lengths | {i.name for i in packet.sorted_items if i.overlap}


def test_the_xtce_names_the_same_containers_parameters_types_units_and_encodings_as_the_cosmos_target(target, tmp_path):
    directory, config = target
    ours = ET.parse(directory / export_ground.XTCE_FILE).getroot()
    assert ours.tag == _x("SpaceSystem") and ours.get("name") == TARGET
    config.to_xtce(str(tmp_path))  # openc3's own XTCE export of the COSMOS target
    theirs = ET.parse(tmp_path / TARGET / "cmd_tlm" / f"{TARGET.lower()}.xtce").getroot()

    our_types, their_types = _types(ours, "Parameter"), _types(theirs, "Parameter")
    our_params = {p.get("name"): p for p in ours.iter(_x("Parameter"))}
    their_params = {p.get("name"): p for p in theirs.iter(_x("Parameter"))}
    our_containers = {c.get("name"): c for c in ours.iter(_x("SequenceContainer"))}
    their_containers = {c.get("name"): c for c in theirs.iter(_x("SequenceContainer"))}
    header = [
        e.get("parameterRef") for e in our_containers[export_ground.XTCE_HEADER_CONTAINER].find("x:EntryList", XTCE_NS)
    ]
    assert header == ["SEQ", "TYPE"]
    compared = 0
    for spec in (s for s in MESSAGES if not s.is_command):
        packet = config.telemetry[TARGET][spec.name]
        lengths = _length_items(packet)
        # the container: ours extends FRAME restricted to the type byte, openc3's extends NAME_Base restricted alike
        mine = our_containers[spec.name]
        assert mine.find("x:BaseContainer", XTCE_NS).get("containerRef") == export_ground.XTCE_HEADER_CONTAINER
        assert _condition(mine.find("x:BaseContainer", XTCE_NS)) == ("TYPE", "==", spec.type_id)
        comparisons = their_containers[spec.name].findall(".//x:Comparison", XTCE_NS)
        assert [(c.get("parameterRef"), int(c.get("value"))) for c in comparisons] == [("TYPE", spec.type_id)]
        entries = mine.find("x:EntryList", XTCE_NS)
        their_entries = [
            e.get("parameterRef") for e in their_containers[f"{spec.name}_Base"].find("x:EntryList", XTCE_NS)
        ]
        # the same parameters in the same order (XTCE folds a length field into the field it sizes)
        want = [export_ground.xtce_parameter_name(spec.name, n) for n in their_entries if n not in lengths]
        assert header + [e.get("parameterRef") for e in entries] == want, spec.name
        for entry, name in zip(entries, [n for n in their_entries if n not in lengths][2:], strict=True):
            item = packet.get_item(name)
            mine_p = our_params[entry.get("parameterRef")]
            variable = bool(item.variable_bit_size)
            ours_t = _type_of(our_types, mine_p.get("parameterTypeRef"), variable)
            theirs_t = _type_of(their_types, their_params[name].get("parameterTypeRef"), variable)
            assert ours_t == theirs_t, (spec.name, name)
            assert (mine_p.get("shortDescription") or "") == export_ground.plain(item.description), (spec.name, name)
            if variable:  # the length item's size is the leading size tag
                tag = our_types[mine_p.get("parameterTypeRef")].find(".//x:LeadingSize", XTCE_NS)
                tag = (
                    tag
                    if tag is not None
                    else our_types[mine_p.get("parameterTypeRef")].find(".//x:AlgorithmText", XTCE_NS)
                )
                length_bits = packet.get_item(item.variable_bit_size["length_item_name"]).bit_size
                assert tag is not None and str(length_bits) in (tag.get("sizeInBitsOfSizeTag") or tag.text), name
            slot = re.match(r"^STAR_(\d{3})_", name)
            if slot:  # a star slot exists in the frame only when N_STARS is larger than its index
                n_stars = export_ground.xtce_parameter_name(spec.name, "N_STARS")
                assert _condition(entry.find("x:IncludeCondition", XTCE_NS)) == (n_stars, ">", int(slot.group(1)))
            else:
                assert entry.find("x:IncludeCondition", XTCE_NS) is None
            compared += 1
    telemetry_fields = sum(len(list(expected_items(s))) - 2 for s in MESSAGES if not s.is_command)
    assert compared == telemetry_fields - 1  # every field but NAK's text length, folded into the text
    # commands: the same arguments, in the same order, with the same types and the type byte assigned
    our_cmds = {c.get("name"): c for c in ours.iter(_x("MetaCommand"))}
    their_cmds = {c.get("name"): c for c in theirs.iter(_x("MetaCommand"))}
    our_atypes, their_atypes = _types(ours, "Argument"), _types(theirs, "Argument")
    base_args = [a.get("name") for a in our_cmds[export_ground.XTCE_HEADER_COMMAND].find("x:ArgumentList", XTCE_NS)]
    assert base_args == ["SEQ", "TYPE"]
    for spec in (s for s in MESSAGES if s.is_command):
        packet = config.commands[TARGET][spec.name]
        lengths = _length_items(packet)
        mine = our_cmds[spec.name]
        assert mine.find("x:BaseMetaCommand", XTCE_NS).get("metaCommandRef") == export_ground.XTCE_HEADER_COMMAND
        assignment = mine.find(".//x:ArgumentAssignment", XTCE_NS)
        assert (assignment.get("argumentName"), int(assignment.get("argumentValue"))) == ("TYPE", spec.type_id)
        their_args = [a for a in their_cmds[f"{spec.name}_Base"].find("x:ArgumentList", XTCE_NS)]
        arguments = mine.findall("x:ArgumentList/x:Argument", XTCE_NS)
        want = [a.get("name") for a in their_args if a.get("name") not in lengths]
        assert base_args + [a.get("name") for a in arguments] == want, spec.name
        their_by_name = {a.get("name"): a for a in their_args}
        for a in arguments:
            variable = bool(packet.get_item(a.get("name")).variable_bit_size)
            ours_t = _type_of(our_atypes, a.get("argumentTypeRef"), variable)
            theirs_t = _type_of(their_atypes, their_by_name[a.get("name")].get("argumentTypeRef"), variable)
            assert ours_t == theirs_t, (spec.name, a.get("name"))


def test_the_cosmos_modbus_target_carries_every_register_of_the_map(target):
    from openc3.packets.packet_config import PacketConfig

    from hostlink.portkit import ground_modbus
    from protocol import modbus_map as mm

    directory, _ = target
    config = PacketConfig()
    for name in (export_ground.MODBUS_CMD, export_ground.MODBUS_TLM):
        config.process_file(str(directory / name), ground_modbus.TARGET)
    assert config.warnings == []
    regmap = mm.load_map()
    kinds = {"uint16": ("UINT", 16), "int16": ("INT", 16), "uint32": ("UINT", 32), "int32": ("INT", 32)}
    kinds |= {"int64": ("INT", 64), "float32": ("FLOAT", 32)}
    telemetry = config.telemetry[ground_modbus.TARGET]
    header_bits = 9 * 8  # MBAP (7 bytes), function code, byte count
    seen = set()
    for packet in telemetry.values():
        if packet.packet_name == "WRITE_RESPONSE":
            continue
        address = config.commands[ground_modbus.TARGET][f"READ_{packet.packet_name}"].get_item("ADDRESS").default
        for reg in regmap.table("input"):
            for k in range(reg.count):
                name = reg.name.upper() if reg.count == 1 else f"STAR_{k:03d}_{reg.name.split('_star_')[1].upper()}"
                item = packet.items.get(name)
                if item is None or item.bit_offset != header_bits + 16 * (reg.element_address(k) - address):
                    continue
                want = ("STRING", 8 * reg.length_bytes) if reg.type == "string" else kinds[reg.type]
                assert (item.data_type, item.bit_size, item.endianness) == (*want, "BIG_ENDIAN"), name
                assert (item.units or "") == reg.units and item.description.startswith(reg.description), name
                if reg.scale is not None:
                    assert item.read_conversion.coeffs == [0.0, reg.scale], name
                seen.add((reg.name, k))
    every = {(reg.name, k) for reg in regmap.table("input") for k in range(reg.count)}
    assert seen == every  # every input register (and every star of the window) is read by some packet
    commands = config.commands[ground_modbus.TARGET]
    for reg in regmap.table("holding"):
        write = commands[f"WRITE_{reg.name.upper()}"]
        assert write.get_item("ADDRESS").id_value == reg.address
        assert write.get_item("QUANTITY").default == reg.width
        item = write.get_item(reg.name.upper())
        assert (item.data_type, item.bit_size, item.endianness) == (*kinds[reg.type], "BIG_ENDIAN"), reg.name
    codes = commands["WRITE_COMMAND"].get_item("COMMAND").states
    assert codes == {c["name"]: int(c["code"]) for c in regmap.commands}
