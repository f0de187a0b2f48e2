"""Test helpers for the ground-system exports (tests/test_ground_*.py): the generated COSMOS target loaded by openc3's
own parser, and the comparison of an openc3-decoded packet with hostlink's decoding of the same message.

Expected values are walked from ``protocol.messages.MESSAGES`` here, independently of the generator's flattening
(``hostlink.portkit.export_ground.packet_items``): a field added to the protocol and not to the exports is a missing
item, a wrong size or a wrong value.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hostlink.portkit.export_ground import COSMOS_CMD, COSMOS_TLM, TARGET, table_item_name, write_ground
from protocol import param_table
from protocol.messages import MAX_STARS, Message, MessageSpec, spec_of

#: The magnitude's calibrated value: COSMOS (and XTCE) multiply the raw millimagnitudes by the double nearest 0.001,
#: hostlink divides them by 1000. Both are correctly rounded, so they differ by the rounding of 0.001 (half an ulp,
#: relative) plus each result's own rounding (half an ulp each): at most 2 ulp of the value.
MAG_ULPS = 2


def load_target(directory: Path):  # noqa: ANN201 - openc3 PacketConfig
    """Generate the exports into ``directory`` and load the COSMOS target as COSMOS's System does: target.txt read
    by openc3's Target, then each command and telemetry file it lists by openc3's PacketConfig."""
    from openc3.packets.packet_config import PacketConfig
    from openc3.system.target import Target

    write_ground(directory)
    target = Target(TARGET, str(directory / Path(COSMOS_TLM).parents[2]))
    assert sorted(target.cmd_tlm_files) == sorted(str(directory / name) for name in (COSMOS_CMD, COSMOS_TLM))
    assert target.ignored_parameters == ["SEQ"] and target.ignored_items == ["SEQ"]
    config = PacketConfig()
    for name in target.cmd_tlm_files:
        config.process_file(name, TARGET)
    return config


def _slot_name(record: str, slot: int, member: str) -> str:
    singular = record[:-1]
    short = member[len(singular) + 1 :] if member.startswith(singular + "_") else member
    return f"{singular}_{slot:03d}_{short}".upper()


def expected_items(spec: MessageSpec) -> Iterator[tuple[str, int, str]]:
    """(item name, bits of one element or 0 if variable, COSMOS data type) of every field of ``spec``, from the
    protocol table."""
    kinds = {"B": "UINT", "?": "UINT", "H": "UINT", "h": "INT", "I": "UINT", "i": "INT", "q": "INT", "f": "FLOAT"}
    sizes = {"B": 8, "?": 8, "H": 16, "h": 16, "I": 32, "i": 32, "q": 64, "f": 32}
    yield "SEQ", 16, "UINT"
    yield "TYPE", 8, "UINT"
    for f in spec.fields:
        if f.fmt == "record":
            for slot in range(int(f.max_count or MAX_STARS)):
                for m in f.record:
                    yield _slot_name(f.name, slot, m.name), sizes[m.fmt], kinds[m.fmt]
        elif f.fmt == "s":
            yield f.name.upper(), 0 if f.variable else 8 * int(f.count), "STRING" if f.text else "BLOCK"
        else:
            yield f.name.upper(), sizes[f.fmt], kinds[f.fmt]


def expected_values(msg: Message, seq: int) -> dict[str, object]:
    """Item name -> the value hostlink decoded (None for a star slot past the frame's stars)."""
    spec = spec_of(msg)
    out: dict[str, object] = {"SEQ": seq, "TYPE": spec.type_id}
    for f in spec.fields:
        if f.length_of is not None:
            target = getattr(msg, f.length_of, None)
            if target is None:  # a record: its members are the message's attributes
                record = next(x for x in spec.fields if x.name == f.length_of)
                target = getattr(msg, record.record[0].name)
            out[f.name.upper()] = len(target.encode("utf-8")) if isinstance(target, str) else len(target)
        elif f.fmt == "record":
            n = len(getattr(msg, f.record[0].name))
            for slot in range(int(f.max_count or MAX_STARS)):
                for m in f.record:
                    out[_slot_name(f.name, slot, m.name)] = getattr(msg, m.name)[slot] if slot < n else None
        else:
            out[f.name.upper()] = getattr(msg, f.name)
    return out


def _same_float(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def mismatches(packet, msg: Message, seq: int) -> list[str]:  # noqa: ANN001 - an identified openc3 Packet
    """Every item of ``packet`` (decoded by openc3) whose value differs from hostlink's ``msg``; [] when all agree.

    Integers and floats: equal (raw and converted); states: raw equal, converted the state's label; a fixed-point
    field: raw = the integer steps of hostlink's value (exactly), converted = hostlink's value (pixels exactly: 2**-10
    is a power of two; magnitudes within MAG_ULPS, and the absent magnitude is the raw sentinel)."""
    spec = spec_of(msg)
    out = []
    if packet.packet_name != spec.name:
        return [f"identified as {packet.packet_name}, hostlink decoded {spec.name}"]
    fixed = {m.name: m.fixed for f in spec.fields for m in f.record if m.fixed is not None}
    fixed |= {f.name: f.fixed for f in spec.fields if f.fixed is not None}
    for name, want in expected_values(msg, seq).items():
        item = packet.get_item(name)
        raw = packet.read_item(item, "RAW")
        conv = packet.read_item(item, "CONVERTED")
        member = re.sub(r"^[A-Z]+_\d{3}_", "", name).lower()
        member = "star_id" if member == "id" else member
        if want is None:
            ok = raw is None and conv is None
        elif member in fixed and re.match(r"^[A-Z]+_\d{3}_", name):
            fp = fixed[member]
            if math.isnan(want):
                ok = fp.absent is not None and raw == fp.absent
            else:
                steps = round(float(want) * fp.steps_per_unit)
                ulp = math.ulp(float(want)) * (MAG_ULPS if fp.absent is not None else 0)
                ok = raw == steps and abs(conv - float(want)) <= ulp
        elif item.states:
            label = {v: k for k, v in item.states.items()}.get(int(want), int(want))
            ok = raw == int(want) and conv == label
        elif isinstance(want, (tuple, list, np.ndarray)):
            ok = len(raw) == len(want) and all(_same_float(float(a), float(b)) for a, b in zip(raw, want, strict=True))
        elif isinstance(want, float):
            ok = _same_float(raw, want) and _same_float(conv, want)
        elif isinstance(want, (bytes, str)):
            ok = (bytes(raw) if isinstance(want, bytes) else raw) == want and type(conv) is type(raw)
        else:
            ok = raw == int(want) and conv == int(want)
        if not ok:
            out.append(f"{spec.name}.{name}: openc3 raw {raw!r} converted {conv!r}, hostlink {want!r}")
    if spec.name == "PARAM_TABLE":  # the table's values, laid over its bytes
        for field, want in param_table.table_to_mapping(msg.table).items():
            got = packet.read(table_item_name(field))
            if not _same_float(got, want):
                out.append(f"{spec.name}.{table_item_name(field)}: openc3 {got!r}, hostlink {want!r}")
    if len(packet.buffer_no_copy()) != 2 + len(_encoded(msg)):
        out.append(f"{spec.name}: buffer of {len(packet.buffer_no_copy())} bytes")
    return out


def _encoded(msg: Message) -> bytes:
    from protocol.messages import encode

    return encode(msg)


def build_interface(plugin: Path, interface: str, variables: dict[str, object]):  # noqa: ANN201 - openc3 interface
    """Interface ``interface`` of the generated plugin.txt, built as COSMOS builds it (InterfaceModel.build), with the
    plugin's ``<%= name %>`` VARIABLEs set to ``variables``."""
    from openc3.config.config_parser import ConfigParser
    from openc3.models.interface_model import InterfaceModel

    text = plugin.read_text()
    for name, value in variables.items():
        text = text.replace(f"<%= {name} %>", str(value))
    resolved = plugin.with_name("plugin.resolved.txt")
    resolved.write_text(text)
    found: dict[str, dict] = {}
    current = None
    for keyword, args in ConfigParser().parse_file(str(resolved)):
        if keyword == "INTERFACE":
            current = args[0]
            found[current] = {"params": args[1:], "protocols": [], "targets": []}
        elif keyword == "PROTOCOL" and current:
            found[current]["protocols"].append(args)
        elif keyword == "MAP_TARGET" and current:
            found[current]["targets"].append(args[0])
    mine = found[interface]
    assert "<%=" not in " ".join(map(str, mine["params"])), "a VARIABLE left unset"
    model = InterfaceModel(
        interface,
        config_params=mine["params"],
        protocols=mine["protocols"],
        target_names=mine["targets"],
        scope="DEFAULT",
    )
    return model.build()
