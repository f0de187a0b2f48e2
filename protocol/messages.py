"""Every message between host and sensor, defined once, with its byte codec (pure: bytes in, messages out).

A message's bytes (``encode(msg)``) start with its type byte (:class:`MsgType`); all integers and floats are
little-endian. These bytes are the payload of a serial frame (``protocol.framing``), of an ISO-TP message on CAN
(``protocol.can_*``), and the meaning behind the Modbus registers (``protocol/modbus_map.json``): a transport may lay
out the fields differently (a DBC signal, a register), but the message and its field values are these.

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

import math
import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import ClassVar

import numpy as np

from protocol.param_table import TABLE_BYTES

#: One fixed-point step of a centroid coordinate [px] (see the module docstring for the error budget).
CENTROID_LSB_PX = 2.0**-10
CENTROID_STEPS_PER_PX = 1024
#: One step of a magnitude [mag]; int16 range is +-32.767 mag.
MAG_LSB = 1e-3
MAG_ABSENT = -32768
#: Longest NAK text [bytes of UTF-8]; longer texts are cut (at a character boundary).
NAK_TEXT_MAX = 120
#: Most stars one centroid frame may carry (the sensor's frame buffer, sized at start-up).
MAX_STARS = 255
#: Order of the estimable parameters in :class:`Estimate` (== onboard.params.ESTIMATE_NAMES; tests pin it).
ESTIMATE_FIELDS: tuple[str, ...] = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "s1", "s2")

#: Wire layout of one star in a :class:`CentroidFrame` (14 bytes).
STAR_DTYPE = np.dtype([("star_id", "<u4"), ("x", "<i4"), ("y", "<i4"), ("mag", "<i2")])


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


# ----------------------------------------------------------------------------------------------------- commands
@dataclass(frozen=True)
class GetStatus:
    """Ask for a :class:`Telemetry` reply."""

    TYPE: ClassVar[MsgType] = MsgType.GET_STATUS
    tag: int = 0


@dataclass(frozen=True)
class StreamControl:
    """Start (``enable``) or stop the centroid stream. Acked; the first frame after the Ack is a fresh one."""

    TYPE: ClassVar[MsgType] = MsgType.STREAM_CONTROL
    tag: int = 0
    enable: bool = True


@dataclass(frozen=True)
class StageBegin:
    """Safe upload step 2a: clear the staging area for a table of ``length`` bytes (== TABLE_BYTES)."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_BEGIN
    tag: int = 0
    length: int = TABLE_BYTES


@dataclass(frozen=True)
class StageChunk:
    """Safe upload step 2b: bytes ``data`` of the table at byte ``offset``."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_CHUNK
    tag: int = 0
    offset: int = 0
    data: bytes = b""


@dataclass(frozen=True)
class StageVerify:
    """Safe upload step 3: the sensor checks the staged bytes against ``crc32`` and their ranges."""

    TYPE: ClassVar[MsgType] = MsgType.STAGE_VERIFY
    tag: int = 0
    crc32: int = 0


@dataclass(frozen=True)
class ReadStaged:
    """Safe upload step 4: reply :class:`ParamTable` with ``bank = STAGED``."""

    TYPE: ClassVar[MsgType] = MsgType.READ_STAGED
    tag: int = 0


@dataclass(frozen=True)
class Commit:
    """Safe upload step 5: write the verified staged set (whose CRC is ``crc32``) to the inactive bank and switch.
    The Ack's ``value`` is the new generation."""

    TYPE: ClassVar[MsgType] = MsgType.COMMIT
    tag: int = 0
    crc32: int = 0


@dataclass(frozen=True)
class ReadActive:
    """Safe upload step 6 (and ``hostlink params``): reply :class:`ParamTable` with ``bank = ACTIVE``."""

    TYPE: ClassVar[MsgType] = MsgType.READ_ACTIVE
    tag: int = 0


@dataclass(frozen=True)
class ReadEstimate:
    """Reply :class:`Estimate` (or Nak NO_ESTIMATE)."""

    TYPE: ClassVar[MsgType] = MsgType.READ_ESTIMATE
    tag: int = 0


# ------------------------------------------------------------------------------------------------------ replies
@dataclass(frozen=True)
class Ack:
    """Command ``command`` (a MsgType value) done. ``value``: the new generation for COMMIT, else 0."""

    TYPE: ClassVar[MsgType] = MsgType.ACK
    tag: int = 0
    command: int = 0
    value: int = 0


@dataclass(frozen=True)
class Nak:
    """Command ``command`` refused with ``code`` (:class:`NakCode`) and a one-line reason ``text``."""

    TYPE: ClassVar[MsgType] = MsgType.NAK
    tag: int = 0
    command: int = 0
    code: int = 0
    text: str = ""


@dataclass(frozen=True)
class Telemetry:
    """Sensor status (reply to GET_STATUS)."""

    TYPE: ClassVar[MsgType] = MsgType.TELEMETRY
    tag: int = 0
    streaming: bool = False
    stage_state: int = StageState.EMPTY
    active_generation: int = 0
    active_crc32: int = 0
    frames_processed: int = 0
    last_frame: int = 0
    estimator_updates: int = 0


@dataclass(frozen=True)
class ParamTable:
    """A parameter set held by the sensor: ``bank`` (:class:`TableBank`), its generation (0 for the staged set),
    the CRC the sensor computed over ``table`` and the TABLE_BYTES (92) table bytes (``protocol.param_table``)."""

    TYPE: ClassVar[MsgType] = MsgType.PARAM_TABLE
    tag: int = 0
    bank: int = TableBank.ACTIVE
    generation: int = 0
    crc32: int = 0
    table: bytes = bytes(TABLE_BYTES)


@dataclass(frozen=True)
class Estimate:
    """The onboard recursive estimate: ``values`` and 1-sigma ``sigma`` (float32, ESTIMATE_FIELDS order, f in mm;
    sigma NaN where unknown), which parameters are estimated (bit i of ``estimated_mask`` = ESTIMATE_FIELDS[i]),
    the generation of the active set the estimator started from, its number of updates and last frame."""

    TYPE: ClassVar[MsgType] = MsgType.ESTIMATE
    tag: int = 0
    status: int = EstimateStatus.NONE
    estimated_mask: int = 0
    base_generation: int = 0
    n_updates: int = 0
    last_frame: int = 0
    values: tuple[float, ...] = (0.0,) * 10
    sigma: tuple[float, ...] = (math.nan,) * 10


# ------------------------------------------------------------------------------------------------------- stream
@dataclass(frozen=True, eq=False)
class CentroidFrame:
    """One exposure: frame counter, exposure mid-time [us since 1970 UTC] and its stars (numpy arrays of equal
    length: ``star_id`` uint32 (0 = not identified), ``x_px``/``y_px`` float64 on the fixed-point grid after a
    round trip, ``mag`` float64 (NaN = none))."""

    TYPE: ClassVar[MsgType] = MsgType.CENTROID_FRAME
    frame: int
    t_us: int
    star_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    x_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    y_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mag: np.ndarray = field(default_factory=lambda: np.zeros(0))

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
    frames_sent: int = 0


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
COMMAND_TYPES = (
    GetStatus,
    StreamControl,
    StageBegin,
    StageChunk,
    StageVerify,
    ReadStaged,
    Commit,
    ReadActive,
    ReadEstimate,
)


# ------------------------------------------------------------------------------------------------ fixed point
def quantise_px(values_px: np.ndarray) -> np.ndarray:
    """Pixels -> int64 fixed-point steps (round half to even). Raises :class:`EncodeError` if not finite."""
    arr = np.asarray(values_px, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise EncodeError("centroid coordinate is not finite")
    return np.rint(arr * CENTROID_STEPS_PER_PX).astype(np.int64)


def dequantise_px(steps: np.ndarray) -> np.ndarray:
    """Fixed-point steps -> pixels (float64, exact)."""
    return np.asarray(steps, dtype=np.float64) * CENTROID_LSB_PX


def quantise_mag(mag: np.ndarray) -> np.ndarray:
    """Magnitudes -> int16 millimag; NaN -> MAG_ABSENT. Raises :class:`EncodeError` outside +-32.767."""
    arr = np.asarray(mag, dtype=np.float64)
    absent = ~np.isfinite(arr)
    steps = np.rint(np.where(absent, 0.0, arr) / MAG_LSB)
    if np.any(np.abs(steps) > 32767):
        raise EncodeError("magnitude outside +-32.767")
    return np.where(absent, MAG_ABSENT, steps).astype(np.int16)


def dequantise_mag(steps: np.ndarray) -> np.ndarray:
    s = np.asarray(steps)
    # divide (not multiply by 1e-3) so that 5100 -> 5.1 exactly as written in a file
    return np.where(s == MAG_ABSENT, np.nan, s.astype(np.float64) / 1000.0)


# ------------------------------------------------------------------------------------------------------ codecs
_TAG = struct.Struct("<BH")  # type, tag
_STREAM_CONTROL = struct.Struct("<BHB")
_STAGE_BEGIN = struct.Struct("<BHH")
_STAGE_CHUNK = struct.Struct("<BHHB")  # + data
_WITH_CRC = struct.Struct("<BHI")
_ACK = struct.Struct("<BHBI")
_NAK = struct.Struct("<BHBBB")  # + text
_TELEMETRY = struct.Struct("<BHBBIIIII")
_PARAM_TABLE = struct.Struct(f"<BHBII{TABLE_BYTES}s")
_ESTIMATE = struct.Struct("<BHBHIII10f10f")
_FRAME_HEAD = struct.Struct("<BIqH")
_END = struct.Struct("<BI")
_TAG_ONLY = {
    MsgType.GET_STATUS: GetStatus,
    MsgType.READ_STAGED: ReadStaged,
    MsgType.READ_ACTIVE: ReadActive,
    MsgType.READ_ESTIMATE: ReadEstimate,
}

#: Bytes of a centroid frame message: FRAME_HEADER_BYTES + n * STAR_DTYPE.itemsize.
FRAME_HEADER_BYTES = _FRAME_HEAD.size


def _check_u(value: int, bits: int, name: str) -> int:
    if not 0 <= int(value) < (1 << bits):
        raise EncodeError(f"{name}={value} does not fit in uint{bits}")
    return int(value)


def nak_text_bytes(text: str) -> bytes:
    """UTF-8 of ``text`` cut to NAK_TEXT_MAX bytes without splitting a character."""
    return text.encode("utf-8")[:NAK_TEXT_MAX].decode("utf-8", "ignore").encode("utf-8")


def encode_frame_message(frame: CentroidFrame) -> bytes:
    """Centroid frame -> bytes (header, then STAR_DTYPE records)."""
    n = frame.n_stars
    if n > MAX_STARS:
        raise EncodeError(f"{n} stars exceed MAX_STARS={MAX_STARS}")
    x, y = quantise_px(frame.x_px), quantise_px(frame.y_px)
    if np.any(np.abs(x) >= 2**31) or np.any(np.abs(y) >= 2**31):
        raise EncodeError("centroid outside the int32 fixed-point range")
    stars = np.empty(n, dtype=STAR_DTYPE)
    stars["star_id"] = frame.star_id
    stars["x"], stars["y"] = x, y
    stars["mag"] = quantise_mag(frame.mag)
    return (
        _FRAME_HEAD.pack(MsgType.CENTROID_FRAME, _check_u(frame.frame, 32, "frame"), int(frame.t_us), n)
        + stars.tobytes()
    )


def decode_frame_message(data: bytes) -> CentroidFrame:
    if len(data) < _FRAME_HEAD.size:
        raise DecodeError("centroid frame shorter than its header")
    _, frame, t_us, n = _FRAME_HEAD.unpack_from(data)
    if len(data) != _FRAME_HEAD.size + n * STAR_DTYPE.itemsize:
        raise DecodeError(f"centroid frame of {n} stars has {len(data)} bytes")
    stars = np.frombuffer(data, dtype=STAR_DTYPE, count=n, offset=_FRAME_HEAD.size)
    return CentroidFrame(
        frame=frame,
        t_us=t_us,
        star_id=stars["star_id"].astype(np.uint32),
        x_px=dequantise_px(stars["x"]),
        y_px=dequantise_px(stars["y"]),
        mag=dequantise_mag(stars["mag"]),
    )


def encode(msg: Message) -> bytes:
    """Message -> bytes (type byte first). Raises :class:`EncodeError` for unrepresentable fields."""
    t = msg.TYPE
    try:
        if isinstance(msg, CentroidFrame):
            return encode_frame_message(msg)
        if isinstance(msg, (GetStatus, ReadStaged, ReadActive, ReadEstimate)):
            return _TAG.pack(t, msg.tag)
        if isinstance(msg, StreamControl):
            return _STREAM_CONTROL.pack(t, msg.tag, 1 if msg.enable else 0)
        if isinstance(msg, StageBegin):
            return _STAGE_BEGIN.pack(t, msg.tag, msg.length)
        if isinstance(msg, StageChunk):
            return _STAGE_CHUNK.pack(t, msg.tag, msg.offset, _check_u(len(msg.data), 8, "chunk length")) + bytes(
                msg.data
            )
        if isinstance(msg, (StageVerify, Commit)):
            return _WITH_CRC.pack(t, msg.tag, msg.crc32)
        if isinstance(msg, Ack):
            return _ACK.pack(t, msg.tag, msg.command, msg.value)
        if isinstance(msg, Nak):
            text = nak_text_bytes(msg.text)
            return _NAK.pack(t, msg.tag, msg.command, msg.code, len(text)) + text
        if isinstance(msg, Telemetry):
            return _TELEMETRY.pack(
                t,
                msg.tag,
                int(msg.streaming),
                msg.stage_state,
                msg.active_generation,
                msg.active_crc32,
                msg.frames_processed,
                msg.last_frame,
                msg.estimator_updates,
            )
        if isinstance(msg, ParamTable):
            if len(msg.table) != TABLE_BYTES:
                raise EncodeError(f"parameter table must be {TABLE_BYTES} bytes, got {len(msg.table)}")
            return _PARAM_TABLE.pack(t, msg.tag, msg.bank, msg.generation, msg.crc32, bytes(msg.table))
        if isinstance(msg, Estimate):
            return _ESTIMATE.pack(
                t,
                msg.tag,
                msg.status,
                msg.estimated_mask,
                msg.base_generation,
                msg.n_updates,
                msg.last_frame,
                *msg.values,
                *msg.sigma,
            )
        if isinstance(msg, EndOfStream):
            return _END.pack(t, msg.frames_sent)
    except struct.error as exc:
        raise EncodeError(f"{type(msg).__name__}: {exc}") from None
    raise EncodeError(f"not a message: {msg!r}")


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Bytes -> message. Raises :class:`DecodeError` for anything malformed (never another exception)."""
    data = bytes(data)
    if not data:
        raise DecodeError("empty message")
    try:
        t = MsgType(data[0])
    except ValueError:
        raise DecodeError(f"unknown message type 0x{data[0]:02x}") from None
    try:
        if t == MsgType.CENTROID_FRAME:
            return decode_frame_message(data)
        if t in _TAG_ONLY:
            return _TAG_ONLY[t](tag=_unpack_exact(_TAG, data)[1])
        if t == MsgType.STREAM_CONTROL:
            _, tag, enable = _unpack_exact(_STREAM_CONTROL, data)
            return StreamControl(tag=tag, enable=bool(enable))
        if t == MsgType.STAGE_BEGIN:
            _, tag, length = _unpack_exact(_STAGE_BEGIN, data)
            return StageBegin(tag=tag, length=length)
        if t == MsgType.STAGE_CHUNK:
            _, tag, offset, n = _STAGE_CHUNK.unpack_from(data)
            if len(data) != _STAGE_CHUNK.size + n:
                raise DecodeError(f"stage chunk says {n} bytes, carries {len(data) - _STAGE_CHUNK.size}")
            return StageChunk(tag=tag, offset=offset, data=data[_STAGE_CHUNK.size :])
        if t in (MsgType.STAGE_VERIFY, MsgType.COMMIT):
            _, tag, crc = _unpack_exact(_WITH_CRC, data)
            return (StageVerify if t == MsgType.STAGE_VERIFY else Commit)(tag=tag, crc32=crc)
        if t == MsgType.ACK:
            _, tag, command, value = _unpack_exact(_ACK, data)
            return Ack(tag=tag, command=command, value=value)
        if t == MsgType.NAK:
            _, tag, command, code, n = _NAK.unpack_from(data)
            if len(data) != _NAK.size + n:
                raise DecodeError(f"NAK says {n} text bytes, carries {len(data) - _NAK.size}")
            return Nak(tag=tag, command=command, code=code, text=data[_NAK.size :].decode("utf-8", "replace"))
        if t == MsgType.TELEMETRY:
            _, tag, streaming, stage, gen, crc, frames, last, updates = _unpack_exact(_TELEMETRY, data)
            return Telemetry(
                tag=tag,
                streaming=bool(streaming),
                stage_state=stage,
                active_generation=gen,
                active_crc32=crc,
                frames_processed=frames,
                last_frame=last,
                estimator_updates=updates,
            )
        if t == MsgType.PARAM_TABLE:
            _, tag, bank, gen, crc, table = _unpack_exact(_PARAM_TABLE, data)
            return ParamTable(tag=tag, bank=bank, generation=gen, crc32=crc, table=table)
        if t == MsgType.ESTIMATE:
            v = _unpack_exact(_ESTIMATE, data)
            return Estimate(
                tag=v[1],
                status=v[2],
                estimated_mask=v[3],
                base_generation=v[4],
                n_updates=v[5],
                last_frame=v[6],
                values=tuple(v[7:17]),
                sigma=tuple(v[17:27]),
            )
        if t == MsgType.END_OF_STREAM:
            return EndOfStream(frames_sent=_unpack_exact(_END, data)[1])
    except struct.error as exc:
        raise DecodeError(f"{t.name}: {exc}") from None
    raise DecodeError(f"message type {t.name} has no decoder")  # pragma: no cover - every MsgType is handled


def _unpack_exact(st: struct.Struct, data: bytes) -> tuple:
    if len(data) != st.size:
        raise DecodeError(f"{MsgType(data[0]).name} must be {st.size} bytes, got {len(data)}")
    return st.unpack(data)


def is_command(msg: Message) -> bool:
    return isinstance(msg, COMMAND_TYPES)


def frame_message_bytes(n_stars: int) -> int:
    """Encoded size of a centroid frame message with ``n_stars`` stars [bytes]."""
    return FRAME_HEADER_BYTES + n_stars * STAR_DTYPE.itemsize
