"""The COSMOS target of the sensor's Modbus/TCP link, generated from the Modbus register map
(``protocol/modbus_map.json`` read by ``protocol.modbus_map``), for ``hostlink export-ground``.

COSMOS has no Modbus interface of its own, but Modbus/TCP is a length-prefixed protocol its TCP/IP client interface
frames with its LENGTH protocol: every application data unit starts with the MBAP header (transaction id u16,
protocol id u16 = 0, length u16 = the bytes after it, unit id u8), all big-endian, then the function code. The
packets, from the map alone:

* ``READ_<BLOCK>`` (function code 4, read input registers) for each checked block of the map (result, status,
  active, staged, estimate, window) and its reply ``<BLOCK>``: every register of the block at its place, with the
  map's type (big-endian, most significant word first), unit, scale and description. A reply does not say which
  registers it holds; the request's transaction id, echoed by the reply, does: each block has its own
  (:func:`read_blocks`), and COSMOS identifies the reply by transaction id and function code;
* the stream window's stars: the first read holds the window's head and the first stars that fit in one read
  (at most ``MAX_READ_REGISTERS``); the others are read in pages ``READ_WINDOW_STARS_<P>`` / ``WINDOW_STARS_<P>``;
* ``WRITE_<REGISTER>`` (function code 16, write multiple registers) for each holding register, and
  ``WRITE_STAGE_TABLE`` for the whole staging mailbox at once; the sensor's reply to any write is
  ``WRITE_RESPONSE`` (address and quantity written). Writing ``command`` runs a command (its states are the map's
  command codes), whose result is then read in ``RESULT``.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol import modbus_map as mm

#: The COSMOS target of the Modbus link (its packets are Modbus application data units, not serial messages).
TARGET = "STARTRACKER_MB"
INTERFACE = "STARTRACKER_MODBUS"
#: Modbus/TCP's port (the emulator takes a free one unless told: `hostlink emulate --transport modbus --port`).
DEFAULT_PORT = 502
FC_READ_INPUT = 4
FC_WRITE_MULTIPLE = 16
#: The transaction id of every write (its reply is identified by function code 16 and this id).
WRITE_TRANSACTION_ID = 0x0100
#: The transaction id of the first read block (the next ones count up); window star pages start at WINDOW_PAGE_ID.
FIRST_READ_TRANSACTION_ID = 1
WINDOW_PAGE_TRANSACTION_ID = 0x0040
#: MBAP header bytes and the bytes after the length field that the length counts from: transaction id, protocol id,
#: length (the LENGTH protocol's offset: the ADU is the length value + 6 bytes).
MBAP_LENGTH_OFFSET = 6
#: The staging mailbox's registers (written together by WRITE_STAGE_TABLE).
STAGE_PREFIX = "stage_"

_TYPES: dict[str, tuple[str, int]] = {
    "uint16": ("UINT", 16),
    "int16": ("INT", 16),
    "uint32": ("UINT", 32),
    "int32": ("INT", 32),
    "int64": ("INT", 64),
    "float32": ("FLOAT", 32),
}


@dataclass(frozen=True)
class ReadBlock:
    """One read of input registers: its packet name, transaction id, first address, register count and the map
    entries (with the array elements ``index`` of a star array) it holds."""

    name: str
    transaction_id: int
    address: int
    count: int
    entries: tuple[tuple[mm.Register, int | None], ...]


def _window_stars_in_head(block: mm.CheckedBlock) -> int:
    first, count = block.read_span(0)
    return (mm.MAX_READ_REGISTERS - count) // block.stars_from.stride  # type: ignore[union-attr]


def read_blocks(regmap: mm.ModbusMap | None = None) -> tuple[ReadBlock, ...]:
    """Every read the target defines, from the map's checked blocks (each block with its check register)."""
    regmap = regmap or mm.load_map()
    out = []
    for k, block in enumerate(regmap.checked_blocks):
        first, count = block.read_span(0)
        entries: list[tuple[mm.Register, int | None]] = [
            (r, None) for r in regmap.table("input") if first <= r.address < first + count and r.count == 1
        ]
        if block.stars_from is not None:
            stars = [r for r in regmap.table("input") if r.count > 1 and r.address >= block.stars_from.address]
            n_head = _window_stars_in_head(block)
            count = first + count - first + n_head * block.stars_from.stride
            entries += [(r, i) for i in range(n_head) for r in stars]
            out.append(ReadBlock(block.name.upper(), FIRST_READ_TRANSACTION_ID + k, first, count, tuple(entries)))
            per_page = mm.MAX_READ_REGISTERS // block.stars_from.stride
            page, star = 1, n_head
            while star < block.stars_from.count:
                n = min(per_page, block.stars_from.count - star)
                address = block.stars_from.address + star * block.stars_from.stride
                page_entries = tuple((r, i) for i in range(star, star + n) for r in stars)
                name = f"{block.name.upper()}_STARS_{page}"
                out.append(
                    ReadBlock(
                        name, WINDOW_PAGE_TRANSACTION_ID + page, address, n * block.stars_from.stride, page_entries
                    )
                )
                page, star = page + 1, star + n
            continue
        out.append(ReadBlock(block.name.upper(), FIRST_READ_TRANSACTION_ID + k, first, count, tuple(entries)))
    return tuple(out)


def item_name(reg: mm.Register, index: int | None) -> str:
    """The COSMOS item of a register (``STATUS_STREAMING``) or of element ``index`` of a star array
    (``window_star_x_px`` element 3 -> ``STAR_003_X_PX``)."""
    if index is None:
        return reg.name.upper()
    member = reg.name.split("_star_", 1)[1]
    return f"STAR_{index:03d}_{member.upper()}"


def _quote(text: str) -> str:
    return '"' + " ".join(text.replace('"', "'").split()) + '"'


def _mbap(command: bool, transaction_id: int, function_code: int, unit_id: int) -> list[str]:
    if command:
        return [
            f"  APPEND_ID_PARAMETER TRANSACTION_ID 16 UINT 0 65535 {transaction_id} "
            '"MBAP transaction id: the reply echoes it (the reply packet is identified by it)"',
            '  APPEND_PARAMETER PROTOCOL_ID 16 UINT 0 0 0 "MBAP protocol id (0 = Modbus)"',
            '  APPEND_PARAMETER LENGTH 16 UINT 0 65535 0 "MBAP length: bytes after this field (filled on sending)"',
            f'  APPEND_PARAMETER UNIT_ID 8 UINT 0 255 {unit_id} "Modbus unit (slave) id"',
            f'  APPEND_ID_PARAMETER FUNCTION_CODE 8 UINT 0 255 {function_code} "Modbus function code"',
        ]
    return [
        f'  APPEND_ID_ITEM TRANSACTION_ID 16 UINT {transaction_id} "MBAP transaction id, echoed from the request"',
        '  APPEND_ITEM PROTOCOL_ID 16 UINT "MBAP protocol id (0 = Modbus)"',
        '  APPEND_ITEM LENGTH 16 UINT "MBAP length: bytes after this field"',
        '  APPEND_ITEM UNIT_ID 8 UINT "Modbus unit (slave) id"',
        f'  APPEND_ID_ITEM FUNCTION_CODE 8 UINT {function_code} "Modbus function code"',
    ]


#: Bits of the MBAP header and function code.
_HEADER_BITS = 8 * 8


def _register_item(reg: mm.Register, index: int | None, bit_offset: int, command: bool) -> list[str]:
    name = item_name(reg, index)
    desc = reg.description + (f" (star {index})" if index is not None else "")
    if reg.type == "string":
        bits = 8 * reg.length_bytes
        line = f"  ITEM {name} {bit_offset} {bits} STRING {_quote(desc)}"
    else:
        data_type, bits = _TYPES[reg.type]
        if command:  # MIN / MAX: the type's whole range (COSMOS's constants)
            line = f"  APPEND_PARAMETER {name} {bits} {data_type} MIN MAX 0 {_quote(desc)}"
        else:
            line = f"  ITEM {name} {bit_offset} {bits} {data_type} {_quote(desc)}"
    out = [line]
    if reg.scale is not None:
        out.append(f"    POLY_READ_CONVERSION 0.0 {float(reg.scale)!r}")
    if reg.units:
        out.append(f"    UNITS {reg.units} {reg.units}")
    return out


BANNER = (
    "# {name}: generated by `hostlink export-ground` from the star-sensor companion's Modbus register map\n"
    "# (protocol/modbus_map.json, docs/modbus_map.md). Do not edit: regenerate. docs/ground-systems.md explains its\n"
    "# use.\n"
)


def cosmos_modbus_cmd_tlm(regmap: mm.ModbusMap | None = None) -> tuple[str, str]:
    """(cmd.txt, tlm.txt) of the Modbus target."""
    regmap = regmap or mm.load_map()
    unit = regmap.unit_id
    cmd, tlm = [BANNER.format(name="cmd.txt")], [BANNER.format(name="tlm.txt")]
    for rb in read_blocks(regmap):
        cmd.append(f"COMMAND {TARGET} READ_{rb.name} BIG_ENDIAN {_quote(f'read the {rb.name} input registers')}")
        cmd += _mbap(True, rb.transaction_id, FC_READ_INPUT, unit)
        cmd.append(f'  APPEND_PARAMETER ADDRESS 16 UINT 0 65535 {rb.address} "first input register"')
        cmd.append(f'  APPEND_PARAMETER COUNT 16 UINT 1 {mm.MAX_READ_REGISTERS} {rb.count} "registers to read"')
        cmd.append("")
        last = rb.address + rb.count - 1
        what = f"the reply to READ_{rb.name}: input registers {rb.address}..{last}"
        tlm.append(f"TELEMETRY {TARGET} {rb.name} BIG_ENDIAN {_quote(what)}")
        tlm += _mbap(False, rb.transaction_id, FC_READ_INPUT, unit)
        tlm.append('  APPEND_ITEM BYTE_COUNT 8 UINT "bytes of register data that follow"')
        for reg, index in rb.entries:
            address = reg.element_address(index) if index is not None else reg.address
            tlm += _register_item(reg, index, _HEADER_BITS + 8 + 16 * (address - rb.address), False)
        tlm.append("")
    codes = {c["name"]: int(c["code"]) for c in regmap.commands}
    holding = regmap.table("holding")
    stage = [r for r in holding if r.name.startswith(STAGE_PREFIX)]
    groups = [(r.name.upper(), [r]) for r in holding] + [("STAGE_TABLE", stage)]
    for name, regs in groups:
        width = sum(r.width for r in regs)
        desc = regs[0].description if len(regs) == 1 else "the whole staging mailbox (the table a STAGE_CHUNK sends)"
        cmd.append(f"COMMAND {TARGET} WRITE_{name} BIG_ENDIAN {_quote('write ' + desc)}")
        cmd += _mbap(True, WRITE_TRANSACTION_ID, FC_WRITE_MULTIPLE, unit)
        cmd.append(f'  APPEND_ID_PARAMETER ADDRESS 16 UINT 0 65535 {regs[0].address} "first holding register"')
        cmd.append(f'  APPEND_PARAMETER QUANTITY 16 UINT {width} {width} {width} "registers written"')
        cmd.append(f'  APPEND_PARAMETER BYTE_COUNT 8 UINT {2 * width} {2 * width} {2 * width} "bytes that follow"')
        for r in regs:
            cmd += _register_item(r, None, 0, True)
            if r.name == "command":
                cmd += [f"    STATE {c} {v}" for c, v in codes.items()]
        cmd.append("")
    tlm.append(f'TELEMETRY {TARGET} WRITE_RESPONSE BIG_ENDIAN "the sensor\'s reply to a write"')
    tlm += _mbap(False, WRITE_TRANSACTION_ID, FC_WRITE_MULTIPLE, unit)
    tlm.append('  APPEND_ITEM ADDRESS 16 UINT "first holding register written"')
    tlm.append('  APPEND_ITEM QUANTITY 16 UINT "registers written"')
    tlm.append("")
    return "\n".join(cmd), "\n".join(tlm)


def length_protocol_args() -> list[str]:
    """LengthProtocol's arguments for Modbus/TCP: the MBAP length (bits 32..47, big-endian) counts the bytes after
    it, so an ADU is length + 6 bytes; nothing discarded, no sync pattern, no maximum, the length filled on
    sending."""
    return ["32", "16", str(MBAP_LENGTH_OFFSET), "1", "BIG_ENDIAN", "0", "nil", "nil", "TRUE"]


def cosmos_modbus_target_txt() -> str:
    """target.txt of the Modbus target: the MBAP fields the interface fills are hidden from the command sender."""
    hidden = "".join(f"IGNORE_PARAMETER {name}\n" for name in ("PROTOCOL_ID", "LENGTH"))
    return BANNER.format(name="target.txt") + "LANGUAGE python\n" + hidden


def cosmos_modbus_plugin_lines() -> list[str]:
    """The Modbus target and its TCP/IP client interface, for plugin.txt."""
    return [
        f"TARGET {TARGET} {TARGET}",
        "",
        "# Modbus/TCP: the MBAP header's length field frames each reply (COSMOS's LENGTH protocol)",
        f"INTERFACE {INTERFACE} openc3/interfaces/tcpip_client_interface.py <%= modbus_host %> <%= modbus_port %> "
        "<%= modbus_port %> 10.0 nil LENGTH " + " ".join(length_protocol_args()),
        f"  MAP_TARGET {TARGET}",
        "",
    ]
