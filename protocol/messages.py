"""Every message between host and sensor, defined once, with its byte codec (pure: bytes in, messages out).

Each message is ONE frozen dataclass whose fields carry their wire layout (:func:`wire`: struct format character,
element count or length rule, unit); :data:`MESSAGES` is the table derived from those classes, and one generic
:func:`encode` and one generic :func:`decode` walk it. Nothing else describes a message: a C exporter, a Modbus or CAN
layout, or a fuzzer reads :data:`MESSAGES` (``MessageSpec.type_id``, ``.name``, ``.fields``: ordered
:class:`WireField` with ``name``, ``fmt``, ``count``, ``length_of``, ``record``).

A message's bytes (``encode(msg)``) start with its type byte (:class:`MsgType`, uint8), then its fields in order;
all integers and floats are little-endian, with the sizes of Python's ``struct`` standard mode (``<``):
``B`` uint8, ``?`` bool (one byte, 0/1), ``H`` uint16, ``h`` int16, ``I`` uint32, ``i`` int32, ``q`` int64,
``f`` float32 (IEEE-754), ``s`` raw bytes. A field has a fixed ``count`` (an integer) or a variable one: then
``count`` names the earlier length field (``length_of`` the variable field) that gives the number of elements. A
``record`` field is an array of records whose members are the listed fields (a C array of packed structs).
These bytes are the payload of a serial frame (``protocol.framing``), of an ISO-TP message on CAN
(``protocol.can_frames``), and the meaning behind the Modbus registers (``protocol/modbus_map.json``): a transport may
lay out the fields differently (a DBC signal, a register), but the message and its field values are these.

Centroids travel in fixed point: ``x_px = n * CENTROID_LSB_PX`` with ``n`` an integer, ``CENTROID_LSB_PX = 2**-10``
px (int32 on serial: range +-2 097 152 px). Rounding to the nearest step adds a uniform error of standard deviation
``2**-10 / sqrt(12) = 2.8e-4 px``; against 0.01 px centroid noise the total grows from 0.01 to
``sqrt(0.01**2 + 2.8e-4**2) = 0.0100040`` px (+0.04 %), below what any calibration can measure (tests pin it).
Magnitudes travel as int16 millimagnitudes (``MAG_ABSENT`` = no magnitude), times as int64 microseconds since
1970-01-01T00:00:00 UTC, leap seconds not counted (POSIX time).

Request/reply: every command carries a ``tag`` (uint16) that its reply (:class:`Ack`, :class:`Nak`, or the data
reply) echoes, so a host never mistakes a late reply for the answer to a newer command. Stream messages
(:class:`CentroidFrame`, :class:`EndOfStream`) are unsolicited.

Error codes (:class:`NakCode`) say why a command was refused; :class:`Nak` also carries a one-line text (UTF-8, at
most ``NAK_TEXT_MAX`` bytes) such as ``principal_point_px[0]: 5000.0 is off the detector [-0.5, 2047.5]``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np

from protocol.param_table import TABLE_BYTES

#: One fixed-point step of a centroid coordinate [px] (see the module docstring for the error budget).
CENTROID_LSB_PX = 2.0**-10
CENTROID_STEPS_PER_PX = 1024
#: One step of a magnitude [mag]; int16 range is +-32.767 mag.
MAG_LSB = 1e-3
MAG_STEPS_PER_MAG = 1000
MAG_ABSENT = -32768
#: Longest NAK text [bytes of UTF-8]; longer texts are cut (at a character boundary).
NAK_TEXT_MAX = 120
#: Most stars one centroid frame may carry (the sensor's frame buffer, sized at start-up).
MAX_STARS = 255
#: Order of the estimable parameters in :class:`Estimate` (== onboard.params.ESTIMATE_NAMES; tests pin it).
ESTIMATE_FIELDS: tuple[str, ...] = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "s1", "s2")
#: Struct format of the type byte that starts every message.
TYPE_FORMAT = "B"


class DecodeError(ValueError):
    """Bytes that are not a valid message (unknown type, wrong length, bad field)."""


class EncodeError(ValueError):
    """A message whose fields cannot be represented on the wire (e.g. a centroid outside the fixed-point range)."""


class MsgType(IntEnum):
    """First byte of every message. Commands (host -> sensor) < 0x80 <= replies and stream messages."""

    GET_STATUS = 0x01
    STREAM_CONTROL = 0x02
    STAGE_BEGIN = 0x03
    STAGE_CHUNK = 0x04
    STAGE_VERIFY = 0x05
    READ_STAGED = 0x06
    COMMIT = 0x07
    READ_ACTIVE = 0x08
    READ_ESTIMATE = 0x09
    ACK = 0x80
    NAK = 0x81
    TELEMETRY = 0x82
    PARAM_TABLE = 0x83
    ESTIMATE = 0x84
    CENTROID_FRAME = 0x90
    END_OF_STREAM = 0x91


class NakCode(IntEnum):
    """Why the sensor refused a command."""

    UNKNOWN_COMMAND = 1  # type byte not a command, or not valid in this transport
    BAD_LENGTH = 2  # stage length is not a parameter table, or a chunk runs past its end
    NOT_STAGED = 3  # verify/read/commit without a complete staged set
    BAD_CRC = 4  # the staged bytes do not match the CRC the host sent
    INVALID_PARAMS = 5  # the staged set fails the range checks (onboard.params.validate_params)
    NOT_VERIFIED = 6  # commit before a successful verify, or of a different set than was verified
    NO_ESTIMATE = 7  # the onboard estimator has no estimate yet
    BANK_WRITE_FAILED = 8  # the inactive bank did not read back with a valid CRC: nothing was switched
    BUSY = 9  # the command cannot run now (e.g. a transport-specific limit)
    # COMMIT whose nonce is not the current staging session's, or whose expected_generation is not the active one:
    # nothing was switched (a recorded, stale or reordered upload)
    STALE_SESSION = 10


class StageState(IntEnum):
    """Staging area of the parameter banks."""

    EMPTY = 0
    RECEIVING = 1  # begun, chunks arriving (or complete but not verified)
    VERIFIED = 2  # complete, CRC and ranges checked: may be committed


class TableBank(IntEnum):
    STAGED = 0
    ACTIVE = 1


class EstimateStatus(IntEnum):
    NONE = 0  # no estimator, or no update yet
    RUNNING = 1


# ------------------------------------------------------------------------------------------ wire description
@dataclass(frozen=True)
class FixedPoint:
    """A physical quantity sent as integer steps: ``value = steps / steps_per_unit``; ``absent`` (if set) is the
    step value that stands for "no value" (NaN)."""

    steps_per_unit: int
    absent: int | None = None


#: Centroid coordinates: 2**-10 px steps. Magnitudes: millimagnitudes, MAG_ABSENT = none.
PX_FIXED = FixedPoint(CENTROID_STEPS_PER_PX)
MAG_FIXED = FixedPoint(MAG_STEPS_PER_MAG, MAG_ABSENT)

_FORMAT_BYTES = {"B": 1, "?": 1, "H": 2, "h": 2, "I": 4, "i": 4, "q": 8, "f": 4, "s": 1}
_INT_RANGE = {"B": (0, 255), "H": (0, 65535), "h": (-32768, 32767), "I": (0, 2**32 - 1), "i": (-(2**31), 2**31 - 1)}
_INT_RANGE["q"] = (-(2**63), 2**63 - 1)


@dataclass(frozen=True)
class WireField:
    """One field of a message on the wire, in order after the type byte.

    ``fmt``: struct format character (little-endian, see the module docstring), ``"record"`` for an array of records
    (members in ``record``). ``count``: number of elements (1 = a scalar; for ``s`` the byte count), or the name of the
    earlier length field holding it. ``length_of``: this (wire-only) field is the element count of the named field.
    ``max_count``: most elements a variable field may hold (bytes of UTF-8 for a text). ``text``: bytes are UTF-8
    text. ``fixed``: an integer field carrying a physical quantity in :class:`FixedPoint` steps. ``unit``: of the
    physical value."""

    name: str
    fmt: str
    count: int | str = 1
    unit: str = ""
    doc: str = ""
    length_of: str | None = None
    max_count: int | None = None
    text: bool = False
    fixed: FixedPoint | None = None
    record: tuple[WireField, ...] = ()

    @property
    def variable(self) -> bool:
        return isinstance(self.count, str)

    @property
    def element_bytes(self) -> int:
        """Bytes of one element (one record for a record field)."""
        if self.fmt == "record":
            return sum(m.element_bytes for m in self.record)
        return _FORMAT_BYTES[self.fmt]


@dataclass(frozen=True)
class MessageSpec:
    """One message of the table: its type byte, name, class and ordered wire fields (after the type byte)."""

    type_id: int
    name: str
    cls: type
    fields: tuple[WireField, ...]
    doc: str = ""

    @property
    def is_command(self) -> bool:
        return self.type_id < 0x80

    @property
    def fixed_bytes(self) -> int:
        """Bytes of the message with every variable field empty (type byte included)."""
        return 1 + sum(f.element_bytes * f.count for f in self.fields if not f.variable)  # type: ignore[operator]


_WIRE = "wire"


def wire(
    fmt: str,
    default: Any = dataclasses.MISSING,
    *,
    count: int = 1,
    unit: str = "",
    doc: str = "",
    length: tuple[str, str] | None = None,
    max_count: int | None = None,
    text: bool = False,
    fixed: FixedPoint | None = None,
    record: str | None = None,
    factory: Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field with its wire layout. ``length=(name, fmt)``: the field is variable, preceded on the wire by
    a length field ``name`` of format ``fmt``; ``record``: consecutive fields with the same record name travel as
    one array of records (the first member carries ``length``)."""
    meta = {
        _WIRE: {
            "fmt": fmt,
            "count": count,
            "unit": unit,
            "doc": doc,
            "length": length,
            "max_count": max_count,
            "text": text,
            "fixed": fixed,
            "record": record,
        }
    }
    return dataclasses.field(default=default, default_factory=factory, metadata=meta)


def _tag() -> Any:
    return wire("H", 0, doc="echoed by the reply")


# ----------------------------------------------------------------------------------------------------- commands
@dataclass(frozen=True)
class GetStatus:
    """Ask for a :class:`Telemetry` reply."""

    TYPE: ClassVar[MsgType] = MsgType.GET_STATUS
    tag: int = _tag()


@dataclass(frozen=True)
class StreamControl:
    """Start (``enable``) or stop the centroid stream. Acked; the first frame after the Ack is a fresh one."""

    TYPE: ClassVar[MsgType] = MsgType.STREAM_CONTROL
    tag: int = _tag()
    enable: bool = wire("?", True, doc="1 = start the stream, 0 = stop it")


@dataclass(frozen=True)
class StageBegin:
    """Safe upload step 2a: clear the staging area for a table of ``length`` bytes (== TABLE_BYTES). The Ack's
    ``value`` is the staging nonce that this upload's COMMIT must carry."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_BEGIN
    tag: int = _tag()
    length: int = wire("H", TABLE_BYTES, unit="byte", doc="length of the table to stage")


@dataclass(frozen=True)
class StageChunk:
    """Safe upload step 2b: bytes ``data`` of the table at byte ``offset``."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_CHUNK
    tag: int = _tag()
    offset: int = wire("H", 0, unit="byte", doc="position of data in the table")
    data: bytes = wire("s", b"", length=("n_bytes", "B"), max_count=255, doc="table bytes")


@dataclass(frozen=True)
class StageVerify:
    """Safe upload step 3: the sensor checks the staged bytes against ``crc32`` and their ranges."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_VERIFY
    tag: int = _tag()
    crc32: int = wire("I", 0, doc="CRC-32 of the staged table")


@dataclass(frozen=True)
class ReadStaged:
    """Safe upload step 4: reply :class:`ParamTable` with ``bank = STAGED``."""

    TYPE: ClassVar[MsgType] = MsgType.READ_STAGED
    tag: int = _tag()


@dataclass(frozen=True)
class Commit:
    """Safe upload step 5: write the verified staged set (whose CRC is ``crc32``) to the inactive bank and switch,
    only if ``nonce`` is the current staging session's (the Ack.value of its STAGE_BEGIN) and the active generation
    is still ``expected_generation`` (else Nak STALE_SESSION). The Ack's ``value`` is the new generation."""

    TYPE: ClassVar[MsgType] = MsgType.COMMIT
    tag: int = _tag()
    crc32: int = wire("I", 0, doc="CRC-32 of the verified staged table")
    nonce: int = wire("I", 0, doc="Ack.value of this upload's STAGE_BEGIN (the staging session)")
    expected_generation: int = wire("I", 0, doc="active generation the host read before staging (0 = none)")


@dataclass(frozen=True)
class ReadActive:
    """Safe upload step 6 (and ``hostlink params``): reply :class:`ParamTable` with ``bank = ACTIVE``."""

    TYPE: ClassVar[MsgType] = MsgType.READ_ACTIVE
    tag: int = _tag()


@dataclass(frozen=True)
class ReadEstimate:
    """Reply :class:`Estimate` (or Nak NO_ESTIMATE)."""

    TYPE: ClassVar[MsgType] = MsgType.READ_ESTIMATE
    tag: int = _tag()


# ------------------------------------------------------------------------------------------------------ replies
@dataclass(frozen=True)
class Ack:
    """Command ``command`` (a MsgType value) done. ``value``: the new generation for COMMIT, the staging nonce for
    STAGE_BEGIN (never 0), else 0."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    tag: int = _tag()
    command: int = wire("B", 0, doc="MsgType of the command")
    value: int = wire("I", 0, doc="new generation (COMMIT), staging nonce (STAGE_BEGIN), else 0")


@dataclass(frozen=True)
class Nak:
    """Command ``command`` refused with ``code`` (:class:`NakCode`) and a one-line reason ``text``."""

    TYPE: ClassVar[MsgType] = MsgType.NAK
    tag: int = _tag()
    command: int = wire("B", 0, doc="MsgType of the command")
    code: int = wire("B", 0, doc="NakCode")
    text: str = wire("s", "", length=("text_bytes", "B"), max_count=NAK_TEXT_MAX, text=True, doc="reason, UTF-8")


@dataclass(frozen=True)
class Telemetry:
    """Sensor status (reply to GET_STATUS)."""

    TYPE: ClassVar[MsgType] = MsgType.TELEMETRY
    tag: int = _tag()
    streaming: bool = wire("?", False, doc="the centroid stream is on")
    stage_state: int = wire("B", StageState.EMPTY, doc="StageState")
    active_generation: int = wire("I", 0, doc="generation of the active parameter set")
    active_crc32: int = wire("I", 0, doc="CRC-32 of the active parameter table")
    frames_processed: int = wire("I", 0, doc="frames the sensor has processed since start-up")
    last_frame: int = wire("I", 0, doc="frame counter of the last frame processed")
    estimator_updates: int = wire("I", 0, doc="updates of the onboard recursive estimator")


@dataclass(frozen=True)
class ParamTable:
    """A parameter set held by the sensor: ``bank`` (:class:`TableBank`), its generation (0 for the staged set),
    the CRC the sensor computed over ``table`` and the TABLE_BYTES (92) table bytes (``protocol.param_table``)."""

    TYPE: ClassVar[MsgType] = MsgType.PARAM_TABLE
    tag: int = _tag()
    bank: int = wire("B", TableBank.ACTIVE, doc="TableBank")
    generation: int = wire("I", 0, doc="generation of the set (0 for the staged set)")
    crc32: int = wire("I", 0, doc="CRC-32 the sensor computed over the table bytes")
    table: bytes = wire("s", bytes(TABLE_BYTES), count=TABLE_BYTES, doc="protocol.param_table bytes")


@dataclass(frozen=True)
class Estimate:
    """The onboard recursive estimate: ``values`` and 1-sigma ``sigma`` (float32, ESTIMATE_FIELDS order, f in mm;
    sigma NaN where unknown), which parameters are estimated (bit i of ``estimated_mask`` = ESTIMATE_FIELDS[i]),
    the generation of the active set the estimator started from, its number of updates and last frame."""

    TYPE: ClassVar[MsgType] = MsgType.ESTIMATE
    tag: int = _tag()
    status: int = wire("B", EstimateStatus.NONE, doc="EstimateStatus")
    estimated_mask: int = wire("H", 0, doc="bit i = ESTIMATE_FIELDS[i] is estimated")
    base_generation: int = wire("I", 0, doc="generation of the active set the estimator started from")
    n_updates: int = wire("I", 0, doc="updates of the estimator")
    last_frame: int = wire("I", 0, doc="frame counter of the estimator's last update")
    values: tuple[float, ...] = wire("f", (0.0,) * 10, count=10, doc="ESTIMATE_FIELDS order, f in mm, x0/y0 in px")
    sigma: tuple[float, ...] = wire("f", (math.nan,) * 10, count=10, doc="1-sigma, NaN = unknown")


# ------------------------------------------------------------------------------------------------------- stream
@dataclass(frozen=True, eq=False)
class CentroidFrame:
    """One exposure: frame counter, exposure mid-time [us since 1970 UTC] and its stars (numpy arrays of equal
    length: ``star_id`` uint32 (0 = not identified), ``x_px``/``y_px`` float64 on the fixed-point grid after a
    round trip, ``mag`` float64 (NaN = none)). On the wire the stars are an array of 14-byte records."""

    TYPE: ClassVar[MsgType] = MsgType.CENTROID_FRAME
    frame: int = wire("I", doc="frame counter")
    t_us: int = wire("q", unit="us", doc="exposure mid-time since 1970-01-01 UTC (POSIX)")
    star_id: np.ndarray = wire(
        "I",
        record="stars",
        length=("n_stars", "H"),
        max_count=MAX_STARS,
        doc="Hipparcos number, 0 = not identified",
        factory=lambda: np.zeros(0, np.uint32),
    )
    x_px: np.ndarray = wire(
        "i", record="stars", fixed=PX_FIXED, unit="px", doc="centroid column", factory=lambda: np.zeros(0)
    )
    y_px: np.ndarray = wire(
        "i", record="stars", fixed=PX_FIXED, unit="px", doc="centroid row", factory=lambda: np.zeros(0)
    )
    mag: np.ndarray = wire(
        "h", record="stars", fixed=MAG_FIXED, unit="mag", doc="magnitude, -32768 = none", factory=lambda: np.zeros(0)
    )

    @property
    def n_stars(self) -> int:
        return int(np.shape(self.star_id)[0])

    def same_as(self, other: CentroidFrame) -> bool:
        """Equal frame, time and stars (NaN magnitudes compare equal)."""
        return (
            self.frame == other.frame
            and self.t_us == other.t_us
            and np.array_equal(self.star_id, other.star_id)
            and np.array_equal(self.x_px, other.x_px)
            and np.array_equal(self.y_px, other.y_px)
            and np.array_equal(self.mag, other.mag, equal_nan=True)
        )


@dataclass(frozen=True)
class EndOfStream:
    """The sensor's frame source is exhausted (replay reached the end of its file) after ``frames_sent`` frames."""

    TYPE: ClassVar[MsgType] = MsgType.END_OF_STREAM
    frames_sent: int = wire("I", 0, doc="frames sent before the source ended")


Message = (
    GetStatus
    | StreamControl
    | StageBegin
    | StageChunk
    | StageVerify
    | ReadStaged
    | Commit
    | ReadActive
    | ReadEstimate
    | Ack
    | Nak
    | Telemetry
    | ParamTable
    | Estimate
    | CentroidFrame
    | EndOfStream
)
MESSAGE_CLASSES: tuple[type, ...] = Message.__args__  # type: ignore[attr-defined]


# ------------------------------------------------------------------------------------------------- the table
def _wire_fields(cls: type) -> tuple[WireField, ...]:
    """The ordered wire fields of a message class, from its dataclass field metadata."""
    out: list[WireField] = []
    members: list[WireField] = []
    record_name: str | None = None
    record_length: tuple[str, str, int | None] | None = None

    def close_record() -> None:
        nonlocal members, record_name, record_length
        if record_name is not None:
            assert record_length is not None, f"{cls.__name__}.{record_name}: first member needs length"
            n_name, n_fmt, n_max = record_length
            out.append(WireField(n_name, n_fmt, length_of=record_name))
            out.append(WireField(record_name, "record", count=n_name, max_count=n_max, record=tuple(members)))
        members, record_name, record_length = [], None, None

    for f in dataclasses.fields(cls):
        w = f.metadata.get(_WIRE)
        if w is None:
            raise TypeError(f"{cls.__name__}.{f.name} has no wire layout")  # pragma: no cover - table invariant
        wf = WireField(
            name=f.name,
            fmt=w["fmt"],
            count=w["count"],
            unit=w["unit"],
            doc=w["doc"],
            max_count=None if w["record"] else w["max_count"],
            text=w["text"],
            fixed=w["fixed"],
        )
        if w["record"] is not None:
            if w["record"] != record_name:
                close_record()
                record_name = w["record"]
                record_length = (*w["length"], w["max_count"])
            members.append(wf)
            continue
        close_record()
        if w["length"] is not None:
            n_name, n_fmt = w["length"]
            out.append(WireField(n_name, n_fmt, length_of=f.name))
            wf = dataclasses.replace(wf, count=n_name)
        out.append(wf)
    close_record()
    return tuple(out)


def _spec(cls: type) -> MessageSpec:
    t = cls.TYPE  # type: ignore[attr-defined]
    return MessageSpec(type_id=int(t), name=t.name, cls=cls, fields=_wire_fields(cls), doc=(cls.__doc__ or "").strip())


#: THE message table, in type-byte order: every message's type byte, name, class and wire fields.
MESSAGES: tuple[MessageSpec, ...] = tuple(sorted((_spec(c) for c in MESSAGE_CLASSES), key=lambda s: s.type_id))
SPEC_BY_TYPE: dict[int, MessageSpec] = {s.type_id: s for s in MESSAGES}
_SPEC_BY_CLASS: dict[type, MessageSpec] = {s.cls: s for s in MESSAGES}
COMMAND_TYPES: tuple[type, ...] = tuple(s.cls for s in MESSAGES if s.is_command)


def spec_of(msg_or_cls: Any) -> MessageSpec:
    """The table entry of a message (instance or class)."""
    cls = msg_or_cls if isinstance(msg_or_cls, type) else type(msg_or_cls)
    return _SPEC_BY_CLASS[cls]


# ------------------------------------------------------------------------------------------------ fixed point
def _quantise(values: Any, fixed: FixedPoint, fmt: str, name: str) -> np.ndarray:
    """Physical values -> int64 steps (round half to even), ``absent`` for NaN where allowed. EncodeError if a
    value is not finite (and cannot be absent) or its steps do not fit ``fmt``."""
    arr = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(arr)
    if fixed.absent is None and not np.all(finite):
        raise EncodeError(f"{name} is not finite")
    steps = np.rint(np.where(finite, arr, 0.0) * fixed.steps_per_unit)
    lo, hi = _INT_RANGE[fmt]
    if fixed.absent is not None:
        lo = max(lo, fixed.absent + 1) if fixed.absent <= lo else lo
    if np.any((steps < lo) | (steps > hi)):
        raise EncodeError(
            f"{name} outside the fixed-point range of {fmt} ({lo / fixed.steps_per_unit:g} to "
            f"{hi / fixed.steps_per_unit:g})"
        )
    steps = steps.astype(np.int64)
    return steps if fixed.absent is None else np.where(finite, steps, fixed.absent)


def _dequantise(steps: Any, fixed: FixedPoint) -> np.ndarray:
    s = np.asarray(steps)
    # divide (not multiply by the step) so that 5100 millimag -> 5.1 exactly as written in a file
    values = s.astype(np.float64) / fixed.steps_per_unit
    return values if fixed.absent is None else np.where(s == fixed.absent, np.nan, values)


def quantise_px(values_px: np.ndarray) -> np.ndarray:
    """Pixels -> int64 fixed-point steps (round half to even). Raises :class:`EncodeError` if not finite."""
    arr = np.asarray(values_px, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise EncodeError("centroid coordinate is not finite")
    return np.rint(arr * CENTROID_STEPS_PER_PX).astype(np.int64)


def dequantise_px(steps: np.ndarray) -> np.ndarray:
    """Fixed-point steps -> pixels (float64, exact)."""
    return _dequantise(steps, PX_FIXED)


def quantise_mag(mag: np.ndarray) -> np.ndarray:
    """Magnitudes -> int16 millimag; NaN -> MAG_ABSENT. Raises :class:`EncodeError` outside +-32.767."""
    return _quantise(mag, MAG_FIXED, "h", "magnitude").astype(np.int16)


def dequantise_mag(steps: np.ndarray) -> np.ndarray:
    """int16 millimag -> magnitudes (float64); MAG_ABSENT -> NaN."""
    return _dequantise(steps, MAG_FIXED)


# ------------------------------------------------------------------------------------------------------ codec
def nak_text_bytes(text: str) -> bytes:
    """UTF-8 of ``text`` cut to NAK_TEXT_MAX bytes without splitting a character."""
    return _text_bytes(text, NAK_TEXT_MAX)


def _text_bytes(text: str, max_bytes: int) -> bytes:
    return str(text).encode("utf-8")[:max_bytes].decode("utf-8", "ignore").encode("utf-8")


_NP_FORMAT = {"B": "u1", "?": "u1", "H": "<u2", "h": "<i2", "I": "<u4", "i": "<i4", "q": "<i8", "f": "<f4"}


@functools.cache
def _record_dtype(f: WireField) -> np.dtype:
    """numpy dtype of one record of a record field (packed, little-endian)."""
    return np.dtype([(m.name, _NP_FORMAT[m.fmt]) for m in f.record])


def _encode_value(f: WireField, value: Any, spec: MessageSpec) -> bytes:
    if f.fmt == "record":
        columns = {m.name: value[m.name] for m in f.record}
        n = len(next(iter(columns.values())))
        out = np.empty(n, dtype=_record_dtype(f))
        for m in f.record:
            col = columns[m.name]
            if np.shape(col) != (n,):
                raise EncodeError(f"{spec.name}.{m.name} has {np.shape(col)} elements, {f.record[0].name} has {n}")
            if m.fixed is not None:
                out[m.name] = _quantise(col, m.fixed, m.fmt, f"{spec.name}.{m.name}")
            else:
                lo, hi = _INT_RANGE[m.fmt]
                ints = np.asarray(col)
                if ints.size and (not np.issubdtype(ints.dtype, np.integer) or ints.min() < lo or ints.max() > hi):
                    raise EncodeError(f"{spec.name}.{m.name} does not fit {m.fmt}")
                out[m.name] = ints
        return out.tobytes()
    if f.fmt == "s":
        if not isinstance(value, (str if f.text else (bytes, bytearray, memoryview))):
            raise EncodeError(
                f"{spec.name}.{f.name} must be {'str' if f.text else 'bytes'}, got {type(value).__name__}"
            )
        data = _text_bytes(value, f.max_count or 255) if f.text else bytes(value)
        if not f.variable and len(data) != f.count:
            raise EncodeError(f"{spec.name}.{f.name} must be {f.count} bytes, got {len(data)}")
        return data
    values = tuple(value) if f.count != 1 else (value,)
    if len(values) != f.count:
        raise EncodeError(f"{spec.name}.{f.name} must have {f.count} elements, got {len(values)}")
    try:
        return struct.pack(f"<{f.count}{f.fmt}", *values)
    except (struct.error, TypeError) as exc:
        raise EncodeError(f"{spec.name}.{f.name}={value!r}: {exc}") from None


def _value_of(spec: MessageSpec, f: WireField, msg: Any) -> Any:
    if f.fmt == "record":
        return {m.name: getattr(msg, m.name) for m in f.record}
    return getattr(msg, f.name)


def _length_of(spec: MessageSpec, target: str, msg: Any) -> int:
    f = next(x for x in spec.fields if x.name == target)
    value = _value_of(spec, f, msg)
    if f.fmt == "record":
        return len(np.atleast_1d(value[f.record[0].name]))
    if f.text:
        return len(_text_bytes(value, f.max_count or 255))
    return len(value)


def encode(msg: Message) -> bytes:
    """Message -> bytes (type byte first), driven by :data:`MESSAGES`. Raises :class:`EncodeError` for fields that
    cannot be represented on the wire."""
    spec = _SPEC_BY_CLASS.get(type(msg))
    if spec is None:
        raise EncodeError(f"not a message: {msg!r}")
    parts = [bytes([spec.type_id])]
    for f in spec.fields:
        if f.length_of is not None:
            n = _length_of(spec, f.length_of, msg)
            target = next(x for x in spec.fields if x.name == f.length_of)
            limit = min(target.max_count if target.max_count is not None else n, _INT_RANGE[f.fmt][1])
            if n > limit:
                raise EncodeError(f"{spec.name}.{f.length_of}: {n} elements exceed {limit}")
            parts.append(struct.pack("<" + f.fmt, n))
        else:
            parts.append(_encode_value(f, _value_of(spec, f, msg), spec))
    return b"".join(parts)


def _decode_value(f: WireField, data: bytes, pos: int, n: int) -> tuple[Any, int]:
    """The value of field ``f`` with ``n`` elements at ``data[pos:]`` and the position after it."""
    end = pos + n * f.element_bytes
    if end > len(data):
        raise DecodeError(f"{f.name}: needs {end} bytes, message has {len(data)}")
    if f.fmt == "record":
        rec = np.frombuffer(data, dtype=_record_dtype(f), count=n, offset=pos)
        out = {}
        for m in f.record:
            col = rec[m.name]
            out[m.name] = _dequantise(col, m.fixed) if m.fixed is not None else col.astype(_NP_FORMAT[m.fmt][-2:])
        return out, end
    if f.fmt == "s":
        raw = data[pos:end]
        if not f.text:
            return raw, end
        try:
            return raw.decode("utf-8"), end  # strict: bytes that are not UTF-8 are a corrupt message, not a text
        except UnicodeDecodeError:
            raise DecodeError(f"{f.name}: not UTF-8") from None
    if f.fmt == "?":  # strict: only 0 and 1 are booleans (anything else is a corrupt byte)
        raw = data[pos:end]
        if any(b > 1 for b in raw):
            raise DecodeError(f"{f.name}: boolean byte not 0 or 1")
        values: tuple = tuple(bool(b) for b in raw)
    else:
        values = struct.unpack_from(f"<{n}{f.fmt}", data, pos)
    return (values[0] if f.count == 1 else values), end


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Bytes -> message, driven by :data:`MESSAGES`. Raises :class:`DecodeError` for anything malformed (never
    another exception)."""
    data = bytes(data)
    if not data:
        raise DecodeError("empty message")
    spec = SPEC_BY_TYPE.get(data[0])
    if spec is None:
        raise DecodeError(f"unknown message type 0x{data[0]:02x}")
    if len(data) < spec.fixed_bytes:
        raise DecodeError(f"{spec.name} must be at least {spec.fixed_bytes} bytes, got {len(data)}")
    pos, counts, kwargs = 1, {}, {}
    for f in spec.fields:
        if f.length_of is not None:
            (n,) = struct.unpack_from("<" + f.fmt, data, pos)
            pos += _FORMAT_BYTES[f.fmt]
            target = next(x for x in spec.fields if x.name == f.length_of)
            if target.max_count is not None and n > target.max_count:
                raise DecodeError(f"{spec.name}.{target.name}: {n} elements exceed {target.max_count}")
            counts[f.length_of] = n
            continue
        n = counts[f.name] if f.variable else int(f.count)  # type: ignore[arg-type]
        value, pos = _decode_value(f, data, pos, n)
        if f.fmt == "record":
            kwargs.update(value)
        else:
            kwargs[f.name] = value
    if pos != len(data):
        raise DecodeError(f"{spec.name} must be {pos} bytes, got {len(data)}")
    return spec.cls(**kwargs)


def is_command(msg: Message) -> bool:
    return isinstance(msg, COMMAND_TYPES)


#: Bytes of a centroid frame message: FRAME_HEADER_BYTES + n * STAR_DTYPE.itemsize.
FRAME_HEADER_BYTES = SPEC_BY_TYPE[MsgType.CENTROID_FRAME].fixed_bytes
#: Wire layout of one star in a :class:`CentroidFrame` (14 bytes).
STAR_DTYPE = _record_dtype(next(f for f in SPEC_BY_TYPE[MsgType.CENTROID_FRAME].fields if f.fmt == "record"))


def frame_message_bytes(n_stars: int) -> int:
    """Encoded size of a centroid frame message with ``n_stars`` stars [bytes]."""
    return FRAME_HEADER_BYTES + n_stars * STAR_DTYPE.itemsize
