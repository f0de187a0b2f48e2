"""The Modbus register map: one data file (``protocol/modbus_map.json``), read here into :class:`ModbusMap`, from
which the emulator's register layout, the host's decoding and the docs page (``docs/modbus_map.md``,
:func:`render_markdown`) are all generated.

Conventions (also written in the JSON, so a client with no project code can follow them):

* addresses are 0-based protocol addresses; ``holding`` = read/write holding registers (function codes 3, 6, 16),
  ``input`` = read-only input registers (function code 4);
* each register is big-endian (Modbus); a 32-bit value (``uint32``, ``int32``, ``float32``) takes two registers with
  the most significant word first (word order ``big``, "ABCD"): float32 1.0 = 0x3F800000 is ``[0x3F80, 0x0000]``;
  ``int64`` takes four registers, most significant first; strings are UTF-8, two bytes per register, high byte
  first, NUL-padded;
* an entry with ``count`` is an array whose element ``i`` starts at ``address + i * stride``; ``scale`` turns the
  integer into the physical value (value = raw * scale).

Pure: text in, layout out; values <-> register lists. No I/O besides reading the package's own data file.
"""

from __future__ import annotations

import importlib.resources
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.crc import crc32
from protocol.param_table import N_FIELDS, PARAM_FIELDS, SIGMA_FIELDS, TABLE_BYTES

MAP_FILE = "modbus_map.json"
TABLES = ("holding", "input")
#: Registers one type occupies.
TYPE_REGISTERS: dict[str, int] = {"uint16": 1, "int16": 1, "uint32": 2, "int32": 2, "float32": 2, "int64": 4}
#: struct format of one value of each type, big-endian (== big word order, big-endian registers).
_STRUCT = {"uint16": ">H", "int16": ">h", "uint32": ">I", "int32": ">i", "float32": ">f", "int64": ">q"}
#: Most registers a single read may return (Modbus application protocol: 125 for function codes 3 and 4).
MAX_READ_REGISTERS = 125
#: Most registers a single write may carry (function code 16: 123).
MAX_WRITE_REGISTERS = 123


class MapError(ValueError):
    """A register map that is inconsistent (overlap, unknown type) or a value that does not fit its register."""


@dataclass(frozen=True)
class Register:
    """One named entry of the map (an array when ``count > 1``)."""

    name: str
    table: str
    address: int
    type: str
    word_order: str
    units: str
    access: str
    description: str
    count: int = 1
    stride: int = 0
    scale: float | None = None
    length_bytes: int = 0

    @property
    def width(self) -> int:
        """Registers of one element."""
        if self.type == "string":
            return (self.length_bytes + 1) // 2
        return TYPE_REGISTERS[self.type]

    @property
    def span(self) -> int:
        """Registers from ``address`` to the end of the last element."""
        return (self.count - 1) * self.stride + self.width if self.count > 1 else self.width

    def element_address(self, i: int) -> int:
        if not 0 <= i < self.count:
            raise IndexError(f"{self.name}[{i}] outside 0..{self.count - 1}")
        return self.address + i * self.stride

    def occupied(self) -> list[int]:
        """Every register address this entry uses."""
        out = []
        for i in range(self.count):
            start = self.address + i * self.stride
            out.extend(range(start, start + self.width))
        return out


@dataclass(frozen=True)
class CheckedBlock:
    """An input-register block read as one snapshot and its check register (``block_check`` in the JSON): registers
    ``first`` .. end of ``last``, then (the stream window) ``stars`` x stride registers from ``stars_from``."""

    name: str
    first: Register
    last: Register
    check: Register
    stars: Register | None = None
    stars_from: Register | None = None

    def read_span(self, n_stars: int = 0) -> tuple[int, int]:
        """(address, count) of the registers a host reads for this block with ``n_stars`` stars (check included)."""
        end = self.check.address + self.check.width
        if self.stars_from is not None and n_stars:
            end = max(end, self.stars_from.address + n_stars * self.stars_from.stride)
        return self.first.address, end - self.first.address


@dataclass(frozen=True)
class ModbusMap:
    """The whole map: registers by name plus the command and NAK code tables."""

    title: str
    unit_id: int
    word_order: str
    word_order_description: str
    addressing: str
    registers: tuple[Register, ...]
    commands: tuple[dict[str, Any], ...]
    nak_codes: tuple[dict[str, Any], ...]
    checked_blocks: tuple[CheckedBlock, ...] = ()
    block_check: str = ""

    def checked_block(self, name: str) -> CheckedBlock:
        for b in self.checked_blocks:
            if b.name == name:
                return b
        raise KeyError(f"no checked block {name!r} in the Modbus map")

    def __getitem__(self, name: str) -> Register:
        for reg in self.registers:
            if reg.name == name:
                return reg
        raise KeyError(f"no register named {name!r} in the Modbus map")

    def table(self, table: str) -> list[Register]:
        return sorted((r for r in self.registers if r.table == table), key=lambda r: r.address)

    def table_size(self, table: str) -> int:
        """Registers the server must provide for ``table`` (one past the highest used address)."""
        return max((r.address + r.span for r in self.table(table)), default=0)

    def command_code(self, name: str) -> int:
        for c in self.commands:
            if c["name"] == name:
                return int(c["code"])
        raise KeyError(f"no command {name!r} in the Modbus map")

    def block(self, table: str, first: str, last: str) -> tuple[int, int]:
        """(address, count) of the contiguous run of registers from entry ``first`` to the end of entry ``last``."""
        a, b = self[first], self[last]
        if a.table != table or b.table != table:
            raise MapError(f"{first}..{last} is not in the {table} table")
        return a.address, b.address + b.span - a.address


def map_text() -> str:
    """The checked-in map file (package data)."""
    return importlib.resources.files("protocol").joinpath(MAP_FILE).read_text(encoding="utf-8")


def parse_map(text: str) -> ModbusMap:
    """Parse and check the JSON map: known tables and types, no two entries sharing a register."""
    doc = json.loads(text)
    regs = []
    for e in doc["registers"]:
        reg = Register(
            name=e["name"],
            table=e["table"],
            address=int(e["address"]),
            type=e["type"],
            word_order=e.get("word_order", "n/a"),
            units=e.get("units", ""),
            access=e.get("access", "r"),
            description=e.get("description", ""),
            count=int(e.get("count", 1)),
            stride=int(e.get("stride", 0)),
            scale=e.get("scale"),
            length_bytes=int(e.get("length_bytes", 0)),
        )
        if reg.table not in TABLES:
            raise MapError(f"{reg.name}: table {reg.table!r} is not one of {TABLES}")
        if reg.type not in TYPE_REGISTERS and reg.type != "string":
            raise MapError(f"{reg.name}: unknown type {reg.type!r}")
        if reg.type == "string" and reg.length_bytes <= 0:
            raise MapError(f"{reg.name}: a string needs length_bytes")
        if reg.width > 1 and reg.type != "string" and reg.word_order != "big":
            raise MapError(f"{reg.name}: word order {reg.word_order!r}; this map uses 'big' (high word first)")
        if reg.count > 1 and reg.stride < reg.width:
            raise MapError(f"{reg.name}: stride {reg.stride} smaller than the element ({reg.width} registers)")
        if reg.table == "input" and reg.access != "r":
            raise MapError(f"{reg.name}: input registers are read-only")
        regs.append(reg)
    for table in TABLES:
        used: dict[int, str] = {}
        for reg in regs:
            if reg.table != table:
                continue
            for a in reg.occupied():
                if a in used:
                    raise MapError(f"{reg.name} and {used[a]} share {table} register {a}")
                if not 0 <= a <= 0xFFFF:
                    raise MapError(f"{reg.name}: address {a} outside 0..65535")
                used[a] = reg.name
    names = [r.name for r in regs]
    if len(set(names)) != len(names):
        raise MapError("duplicate register names")
    by_name = {r.name: r for r in regs}
    blocks = []
    for b in doc.get("checked_blocks", []):
        try:
            blk = CheckedBlock(
                name=b["name"],
                first=by_name[b["first"]],
                last=by_name[b["last"]],
                check=by_name[b["check"]],
                stars=by_name[b["stars"]] if "stars" in b else None,
                stars_from=by_name[b["stars_from"]] if "stars_from" in b else None,
            )
        except KeyError as exc:
            raise MapError(f"checked block {b.get('name')!r}: no register {exc}") from None
        if blk.check.type != "uint32" or blk.check.address != blk.last.address + blk.last.span:
            raise MapError(f"checked block {blk.name}: its check must be a uint32 right after {blk.last.name}")
        if len({blk.first.table, blk.last.table, blk.check.table}) != 1:
            raise MapError(f"checked block {blk.name}: registers in two tables")
        blocks.append(blk)
    return ModbusMap(
        checked_blocks=tuple(blocks),
        block_check=doc.get("block_check", ""),
        title=doc.get("title", "Modbus register map"),
        unit_id=int(doc.get("unit_id", 1)),
        word_order=doc.get("word_order", "big"),
        word_order_description=doc.get("word_order_description", ""),
        addressing=doc.get("addressing", ""),
        registers=tuple(regs),
        commands=tuple(doc.get("commands", [])),
        nak_codes=tuple(doc.get("nak_codes", [])),
    )


_CACHE: dict[str, ModbusMap] = {}


def load_map() -> ModbusMap:
    """The project's map (parsed once)."""
    if "map" not in _CACHE:
        _CACHE["map"] = parse_map(map_text())
    return _CACHE["map"]


# ------------------------------------------------------------------------------------------ values
def to_registers(reg: Register, value: Any) -> list[int]:
    """One element's value -> its registers. Scaled entries take the physical value and round to the step;
    float32 values are rounded to float32. Raises MapError when the value does not fit."""
    if reg.type == "string":
        data = str(value).encode("utf-8")[: reg.length_bytes].ljust(2 * reg.width, b"\0")
        return list(struct.unpack(f">{reg.width}H", data))
    if reg.scale is not None:
        value = round(float(value) / reg.scale)
    elif reg.type != "float32":
        value = int(value)
    try:
        data = struct.pack(_STRUCT[reg.type], value)
    except (struct.error, OverflowError):
        raise MapError(f"{reg.name}: {value!r} does not fit in {reg.type}") from None
    return list(struct.unpack(f">{reg.width}H", data))


def from_registers(reg: Register, words: list[int] | tuple[int, ...]) -> Any:
    """One element's registers -> its value (physical value for scaled entries; str for strings)."""
    if len(words) != reg.width:
        raise MapError(f"{reg.name}: expected {reg.width} registers, got {len(words)}")
    data = struct.pack(f">{reg.width}H", *words)
    if reg.type == "string":
        return data.rstrip(b"\0").decode("utf-8", "replace")
    (value,) = struct.unpack(_STRUCT[reg.type], data)
    if reg.scale is not None:
        return value * reg.scale
    return value


def put(image: list[int], reg: Register, value: Any, index: int = 0) -> None:
    """Write one element into a table image (a mutable list of register values indexed by address)."""
    start = reg.element_address(index)
    image[start : start + reg.width] = to_registers(reg, value)


def get(image: list[int] | np.ndarray, reg: Register, index: int = 0, base: int = 0) -> Any:
    """Read one element from a list of registers that starts at address ``base``."""
    start = reg.element_address(index) - base
    return from_registers(reg, list(image[start : start + reg.width]))


def array_raw(words: np.ndarray, reg: Register, n: int, base: int) -> np.ndarray:
    """The first ``n`` elements of an array entry as raw integers (int64), vectorised: ``words`` is a uint16 array
    of registers starting at address ``base``."""
    w = np.asarray(words, dtype=np.int64)
    idx = reg.address - base + reg.stride * np.arange(n)
    acc = np.zeros(n, dtype=np.int64)
    for k in range(reg.width):
        acc = (acc << 16) | w[idx + k]
    bits = 16 * reg.width
    if reg.type in ("int16", "int32", "int64") and bits < 64:
        acc = np.where(acc >= 1 << (bits - 1), acc - (1 << bits), acc)
    return acc


def block_crc(block: CheckedBlock, words: list[int] | np.ndarray, base: int, n_stars: int = 0) -> int:
    """The check of ``block`` over ``words`` (registers from address ``base``, the block read with its stars):
    CRC-32 of the big-endian bytes of ``first`` .. end of ``last``, then of the ``n_stars`` star records."""
    w = np.asarray(words, dtype=np.int64)
    lo = block.first.address - base
    parts = [w[lo : block.last.address + block.last.span - base]]
    if block.stars_from is not None and n_stars:
        s0 = block.stars_from.address - base
        parts.append(w[s0 : s0 + n_stars * block.stars_from.stride])
    return crc32(np.concatenate(parts).astype(">u2").tobytes())


def block_n_stars(block: CheckedBlock, words: list[int] | np.ndarray, base: int) -> int:
    """Stars the block says it holds (0 for a block without stars)."""
    return 0 if block.stars is None else int(get(words, block.stars, base=base))


def block_intact(block: CheckedBlock, words: list[int] | np.ndarray, base: int) -> bool:
    """True when the block's check register matches its registers (``words`` from ``base``, stars included)."""
    head = block.read_span(0)
    if base > head[0] or base + len(words) < head[0] + head[1]:
        return False  # not even the block's fixed registers were read
    n = block_n_stars(block, words, base)
    if block.stars_from is not None and n > block.stars_from.count:
        return False
    need = block.read_span(n)
    if base > need[0] or base + len(words) < need[0] + need[1]:
        return False
    return int(get(words, block.check, base=base)) == block_crc(block, words, base, n)


def seal_block(block: CheckedBlock, image: list[int]) -> None:
    """Write the block's check into a table image (indexed by address) after its registers changed."""
    put(image, block.check, block_crc(block, image, 0, block_n_stars(block, image, 0)))


def table_from_registers(words: list[int] | np.ndarray) -> bytes:
    """Registers of consecutive float32 entries (high word first) -> the same values as little-endian float32 bytes
    (the parameter table of ``protocol.param_table``), bit for bit (NaN payloads included)."""
    be = np.asarray(words, dtype=np.int64).astype(">u2").tobytes()
    return np.frombuffer(be, dtype=">u4").astype("<u4").tobytes()


def registers_from_table(table: bytes) -> list[int]:
    """Inverse of :func:`table_from_registers`."""
    be = np.frombuffer(bytes(table), dtype="<u4").astype(">u4").tobytes()
    return [int(v) for v in np.frombuffer(be, dtype=">u2")]


def float32_from_words(hi: int, lo: int) -> float:
    """float32 from two registers, high word first (the map's word order)."""
    return struct.unpack(">f", struct.pack(">HH", hi, lo))[0]


# ------------------------------------------------------------------------------------------- docs
def _md(text: str) -> str:
    return str(text).replace("|", "\\|")


def render_markdown(m: ModbusMap) -> str:
    """The docs page (``docs/modbus_map.md``), generated from the map; a test keeps the checked-in page equal."""
    lines = [
        f"# {m.title}",
        "",
        "Generated from `protocol/modbus_map.json` by `protocol.modbus_map.render_markdown` "
        "(`python -m protocol.modbus_map > docs/modbus_map.md`); edit the JSON, not this page.",
        "",
        "## Conventions",
        "",
        f"- Addressing: {m.addressing}.",
        f"- Word order: `{m.word_order}`. {m.word_order_description}",
        f"- Unit (slave) id: {m.unit_id} (`hostlink emulate --unit`).",
        "- Holding registers are read/write (function codes 3, 6, 16); input registers are read-only (4).",
        "- Arrays: element `i` of an entry with `count` starts at `address + i * stride`; value = raw * `scale`.",
        "",
        "## Commands",
        "",
        "Write the code to `command` (after its arguments, or in the same write); the write returns after the "
        "sensor decided. Then read `result_status` (1 ACK, 2 NAK), `result_code`, `result_value`, `result_text`.",
        "",
        "| code | command | uses | does |",
        "|---:|---|---|---|",
    ]
    lines += [
        f"| {c['code']} | {c['name']} | {_md(c.get('uses', ''))} | {_md(c.get('description', ''))} |"
        for c in m.commands
    ]
    if m.checked_blocks:
        lines += ["", "## Block checks", "", m.block_check, "", "| block | first | last | stars | check |"]
        lines += ["|---|---|---|---|---|"]
        for b in m.checked_blocks:
            stars = f"`{b.stars.name}` from `{b.stars_from.name}`" if b.stars and b.stars_from else ""
            lines.append(f"| {b.name} | `{b.first.name}` | `{b.last.name}` | {stars} | `{b.check.name}` |")
    lines += ["", "## NAK codes", "", "| code | name |", "|---:|---|"]
    lines += [f"| {c['code']} | {c['name']} |" for c in m.nak_codes]
    for table in TABLES:
        lines += [
            "",
            f"## {table.capitalize()} registers",
            "",
            "| address | registers | name | type | word order | units | scale | access | description |",
            "|---:|---:|---|---|---|---|---|---|---|",
        ]
        for r in m.table(table):
            addr = f"{r.address}" if r.count == 1 else f"{r.address} + {r.stride} i (i < {r.count})"
            typ = r.type if r.type != "string" else f"string[{r.length_bytes}]"
            scale = "" if r.scale is None else _scale_text(r.scale)
            lines.append(
                f"| {addr} | {r.width} | `{r.name}` | {typ} | {r.word_order} | {_md(r.units)} | {scale} "
                f"| {r.access} | {_md(r.description)} |"
            )
    lines += [
        "",
        "## Worked example: upload a parameter set with any Modbus client",
        "",
        f"1. Write the {N_FIELDS} values, as float32 (two registers each, high word first), to "
        f"`stage_{PARAM_FIELDS[0]}` .. `stage_{PARAM_FIELDS[-1]}`: the camera parameters, then the 1-sigma prior of "
        f"each estimable parameter (`stage_{SIGMA_FIELDS[0]}` ..; NaN or 0 where unknown: the sensor's estimator "
        "then starts that parameter from its cold-start prior).",
        f"2. `command_arg` = {TABLE_BYTES}, `command` = STAGE_BEGIN; then `command_arg` = 0, `command_length` = "
        f"{TABLE_BYTES}, `command` = STAGE_CHUNK.",
        f"3. `command_crc32` = CRC-32 (zlib.crc32) of the {N_FIELDS} values packed as little-endian float32 "
        f"(`struct.pack('<{N_FIELDS}f', ...)`), `command` = STAGE_VERIFY; a refusal gives `result_status` 2 and the "
        "reason.",
        "4. `command` = COMMIT (same `command_crc32`); `result_value` is the new generation.",
        "5. Read `active_generation`, `active_crc32` and `active_*` back.",
        "",
    ]
    return "\n".join(lines)


def _scale_text(scale: float) -> str:
    exponent = math.log2(scale)
    if exponent.is_integer():
        return f"2^{int(exponent)}"
    return f"{scale:g}"


if __name__ == "__main__":  # pragma: no cover - regenerates the docs page
    print(render_markdown(load_map()), end="")
