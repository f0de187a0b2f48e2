"""CAN frame layouts (classic CAN, 11-bit identifiers, 8-byte frames), defined once: the codec and the DBC file
(``protocol/startracker.dbc``, written by :func:`dbc_text`) both come from :data:`CAN_MESSAGES`.

How the messages of ``protocol.messages`` travel on CAN:

* the centroid stream is plain CAN frames, one per star (:data:`STAR`) after one :data:`FRAME_HEADER` per exposure,
  closed by one :data:`FRAME_END` carrying the frame counter and a CRC-32 (:func:`frame_check`) over the exposure
  time, the header and every star payload in order: a receiver accepts a frame only when its FRAME_END matches, so
  a flipped bit in any of its CAN frames (the bus CRC-15 aside, e.g. on an adapter's serial line), a missing or an
  extra star, or a wrong time base is detected within the frame, and loss is counted from the gaps between the
  counters of accepted frames. Exposure times are 24-bit microsecond offsets from the last :data:`TIME_BASE` frame,
  which the sensor sends when a stream starts, whenever an offset would not fit (at most every 16.7 s), and every
  :data:`TIME_BASE_EVERY_FRAMES` frames (so a lost or corrupted time base costs at most that many frames);
* the short commands (every command except STAGE_CHUNK, each at most 7 bytes) travel as one :data:`COMMAND` frame,
  multiplexed by the message type byte, and the sensor's ACK as one :data:`ACK` frame; a parameter can also be staged
  one float per :data:`STAGE_FLOAT` frame (a STAGE_CHUNK of 4 bytes), so a plain DBC tool can drive an upload;
* COMMIT is 15 bytes (its CRC, the staging nonce and the expected generation): the host sends it by ISO-TP; a plain
  DBC tool sends a :data:`COMMIT_BIND` frame (nonce, expected generation) immediately before the COMMAND COMMIT
  frame, and the sensor joins the two (a COMMAND COMMIT without a COMMIT_BIND just before it has nonce 0, which no
  staging session has, and is refused);
* everything longer (STAGE_CHUNK, NAK with its reason, TELEMETRY, PARAM_TABLE, ESTIMATE) is the message's bytes
  (``protocol.messages.encode``) in one ISO-TP message (ISO 15765-2, normal 11-bit addressing) on
  :data:`ISOTP_HOST_TO_SENSOR_ID` / :data:`ISOTP_SENSOR_TO_HOST_ID`; these are not single-frame messages and are not
  in the DBC.

Identifiers are standard (11-bit): the worst-case 8-byte frame is then 135 bits on the bus
(:func:`frame_bits_worst_case`) against 160 for 29-bit identifiers. Lower identifiers win
arbitration, so host commands (0x0A0-0x0A2) and ISO-TP (0x0C0, 0x0C1) go before the stream (0x100-0x103).

Every signal is little-endian (Intel, ``@1`` in the DBC); a frame's 8 bytes are read as one little-endian uint64 and a
signal is ``(u64 >> start) & (2**length - 1)``. Physical value = raw * factor + offset (DBC convention); float32
signals are the raw IEEE-754 bits (``SIG_VALTYPE_ ... : 1``).

Star frames carry the centroid exactly (the ``protocol.messages`` fixed point, 2**-10 px steps) over
``[-512, 7680)`` px, and the Hipparcos number up to 131071; they do NOT carry the magnitude: 64 bits hold
23 + 23 + 17 bits of position and identity plus a 1-bit frame parity, and no magnitude resolution that fits in the
last bit would be worth sending. A CAN stream therefore has ``mag`` = NaN (absent), by design.

Pure: numpy arrays of raw values in, uint64 payloads out, and back. No I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.crc import crc16_ccitt, crc32
from protocol.messages import (
    CENTROID_STEPS_PER_PX,
    MAX_STARS,
    Ack,
    CentroidFrame,
    Commit,
    EncodeError,
    GetStatus,
    Message,
    MsgType,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    dequantise_px,
    quantise_px,
)
from protocol.param_table import PARAM_FIELDS, TABLE_BYTES

#: ISO-TP identifiers (normal addressing, 11-bit): host -> sensor requests, sensor -> host replies.
ISOTP_HOST_TO_SENSOR_ID = 0x0C0
ISOTP_SENSOR_TO_HOST_ID = 0x0C1
#: Classic CAN payload [bytes].
CAN_PAYLOAD_BYTES = 8
#: Time offset field of FRAME_HEADER [bits]: offsets up to 2**24 - 1 us (16.78 s) from the time base.
TIME_OFFSET_BITS = 24
#: Star x/y offset [px] and field width [bits]: raw = steps + 512 * 1024, so x_px in [-512, 7680) travels exactly.
STAR_XY_OFFSET_PX = -512.0
STAR_XY_BITS = 23
STAR_ID_BITS = 17
_XY_RAW_OFFSET = int(-STAR_XY_OFFSET_PX * CENTROID_STEPS_PER_PX)

#: The sensor repeats TIME_BASE at least every this many frames (bounds the frames a lost time base invalidates).
TIME_BASE_EVERY_FRAMES = 16

HOST = "HOST"
SENSOR = "SENSOR"


def frame_bits_worst_case(dlc: int, is_extended_id: bool, is_remote_frame: bool = False) -> int:
    """Bus time of one classic CAN frame with the worst-case number of stuff bits, in bits (ISO 11898-1).

    Stuffed fields: SOF, arbitration (11-bit ID + RTR, or 11 + SRR + IDE + 18 + RTR), control, data, CRC15; that is
    ``34 + 8 n`` bits (standard) or ``54 + 8 n`` (extended) for ``n`` data bytes. At most one stuff bit per 4 bits
    after the first gives ``floor((stuffable - 1) / 4)``. Then 13 unstuffed bits: CRC delimiter, ACK slot and
    delimiter, 7-bit EOF and the 3-bit intermission. Standard, 8 bytes: 98 + 24 + 13 = 135 bits; extended: 160
    (Davis, Burns, Bril & Lukkien 2007, eq. 1).
    """
    n_data = 0 if is_remote_frame else int(dlc)
    stuffable = (54 if is_extended_id else 34) + 8 * n_data
    return stuffable + (stuffable - 1) // 4 + 13


@dataclass(frozen=True)
class CanSignal:
    """One DBC signal (little-endian). ``mux``: multiplexer value this signal is present for (None = always);
    ``is_multiplexer``: the signal that selects them. ``is_float``: raw bits are an IEEE-754 float32."""

    name: str
    start: int
    length: int
    signed: bool = False
    factor: float = 1.0
    offset: float = 0.0
    minimum: float = 0.0
    maximum: float = 0.0
    unit: str = ""
    comment: str = ""
    is_float: bool = False
    is_multiplexer: bool = False
    mux: int | None = None
    choices: tuple[tuple[int, str], ...] = ()

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1


@dataclass(frozen=True)
class CanMessageDef:
    """One single-frame CAN message: identifier, payload length, sender, receivers and signals."""

    name: str
    frame_id: int
    length: int
    sender: str
    receivers: tuple[str, ...]
    signals: tuple[CanSignal, ...]
    comment: str = ""
    _by_name: dict[str, CanSignal] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        self._by_name.update({s.name: s for s in self.signals})

    def signal(self, name: str) -> CanSignal:
        return self._by_name[name]


def _u(name: str, start: int, length: int, **kw: object) -> CanSignal:
    maximum = kw.pop("maximum", float((1 << length) - 1))
    return CanSignal(name, start, length, maximum=maximum, **kw)  # type: ignore[arg-type]


_COMMAND_CHOICES = tuple(
    (int(t), t.name)
    for t in (
        MsgType.GET_STATUS,
        MsgType.STREAM_CONTROL,
        MsgType.STAGE_BEGIN,
        MsgType.STAGE_VERIFY,
        MsgType.READ_STAGED,
        MsgType.COMMIT,
        MsgType.READ_ACTIVE,
        MsgType.READ_ESTIMATE,
    )
)

COMMAND = CanMessageDef(
    "COMMAND",
    0x0A0,
    8,
    HOST,
    (SENSOR,),
    (
        _u(
            "type",
            0,
            8,
            is_multiplexer=True,
            choices=_COMMAND_CHOICES,
            comment="protocol.messages.MsgType of the command",
        ),
        _u("tag", 8, 16, comment="echoed by the reply"),
        _u("enable", 24, 8, mux=int(MsgType.STREAM_CONTROL), maximum=1.0, comment="1 = start the stream"),
        _u("length", 24, 16, mux=int(MsgType.STAGE_BEGIN), unit="byte", comment=f"table length ({TABLE_BYTES})"),
        _u("verify_crc32", 24, 32, mux=int(MsgType.STAGE_VERIFY), comment="CRC-32 of the staged table"),
        _u("commit_crc32", 24, 32, mux=int(MsgType.COMMIT), comment="CRC-32 of the verified staged table"),
    ),
    "A short command (protocol.messages), multiplexed by its type byte; unused bytes are 0.",
)
ACK = CanMessageDef(
    "ACK",
    0x0A1,
    8,
    SENSOR,
    (HOST,),
    (
        _u("type", 0, 8, choices=((int(MsgType.ACK), "ACK"),), comment="always 0x80 (protocol.messages.Ack)"),
        _u("tag", 8, 16, comment="tag of the command"),
        _u("command", 24, 8, choices=_COMMAND_CHOICES + ((int(MsgType.STAGE_CHUNK), "STAGE_CHUNK"),)),
        _u("value", 32, 32, comment="new generation after COMMIT, else 0"),
    ),
    "Command done. A refusal (NAK, with its reason text) comes by ISO-TP.",
)
STAGE_FLOAT = CanMessageDef(
    "STAGE_FLOAT",
    0x0A2,
    8,
    HOST,
    (SENSOR,),
    (
        _u("tag", 0, 16, comment="echoed by the ACK (command STAGE_CHUNK)"),
        _u(
            "field",
            16,
            8,
            maximum=float(len(PARAM_FIELDS) - 1),
            choices=tuple(enumerate(PARAM_FIELDS)),
            comment="index in protocol.param_table.PARAM_FIELDS",
        ),
        _u("reserved", 24, 8, maximum=0.0),
        CanSignal(
            "value",
            32,
            32,
            is_float=True,
            minimum=-3.4e38,
            maximum=3.4e38,
            comment="float32 value of the field (units of the parameter file)",
        ),
    ),
    "Stage one parameter: the STAGE_CHUNK of the 4 table bytes of field `field` (after STAGE_BEGIN).",
)
TIME_BASE = CanMessageDef(
    "TIME_BASE",
    0x102,
    8,
    SENSOR,
    (HOST,),
    (
        CanSignal(
            "t_base_us",
            0,
            64,
            signed=True,
            minimum=-9.2e18,
            maximum=9.2e18,
            unit="us",
            comment="microseconds since 1970-01-01T00:00:00 UTC (POSIX)",
        ),
    ),
    "Time base of the following FRAME_HEADERs; sent when a stream starts and when an offset would not fit.",
)
FRAME_HEADER = CanMessageDef(
    "FRAME_HEADER",
    0x100,
    8,
    SENSOR,
    (HOST,),
    (
        _u("frame", 0, 32, comment="frame counter"),
        _u("n_stars", 32, 8, comment="STAR frames that follow"),
        _u("t_offset_us", 40, TIME_OFFSET_BITS, unit="us", comment="exposure mid-time minus TIME_BASE.t_base_us"),
    ),
    "Start of one centroid frame: its STAR frames follow in order.",
)
STAR = CanMessageDef(
    "STAR",
    0x101,
    8,
    SENSOR,
    (HOST,),
    (
        _u(
            "x_px",
            0,
            STAR_XY_BITS,
            factor=2.0**-10,
            offset=STAR_XY_OFFSET_PX,
            minimum=STAR_XY_OFFSET_PX,
            maximum=STAR_XY_OFFSET_PX + ((1 << STAR_XY_BITS) - 1) * 2.0**-10,
            unit="px",
            comment="centroid column",
        ),
        _u(
            "y_px",
            STAR_XY_BITS,
            STAR_XY_BITS,
            factor=2.0**-10,
            offset=STAR_XY_OFFSET_PX,
            minimum=STAR_XY_OFFSET_PX,
            maximum=STAR_XY_OFFSET_PX + ((1 << STAR_XY_BITS) - 1) * 2.0**-10,
            unit="px",
            comment="centroid row",
        ),
        _u("star_id", 2 * STAR_XY_BITS, STAR_ID_BITS, comment="Hipparcos number, 0 = not identified"),
        _u("frame_parity", 2 * STAR_XY_BITS + STAR_ID_BITS, 1, comment="frame counter mod 2 (catches a lost header)"),
    ),
    "One star of the frame announced by the last FRAME_HEADER. No magnitude (see protocol/can_frames.py).",
)
COMMIT_BIND = CanMessageDef(
    "COMMIT_BIND",
    0x0A3,
    8,
    HOST,
    (SENSOR,),
    (
        _u("nonce", 0, 32, comment="staging nonce: the ACK value of this upload's STAGE_BEGIN"),
        _u("expected_generation", 32, 32, comment="active generation read before staging (0 = none)"),
    ),
    "Binds the COMMAND COMMIT frame that follows it to its staging session (protocol.messages.Commit fields).",
)
FRAME_END = CanMessageDef(
    "FRAME_END",
    0x104,
    8,
    SENSOR,
    (HOST,),
    (
        _u("frame_crc32", 0, 32, comment="CRC-32 of t_us (int64 LE), the FRAME_HEADER and the STAR payloads in order"),
        _u("frame", 32, 32, comment="frame counter (that of the FRAME_HEADER it closes)"),
    ),
    "End of one centroid frame: the receiver accepts the frame only if frame and frame_crc32 match what it received.",
)
END_OF_STREAM = CanMessageDef(
    "END_OF_STREAM",
    0x103,
    8,
    SENSOR,
    (HOST,),
    (
        _u("frames_sent", 0, 16, comment="frames sent, modulo 65536"),
        _u("check", 16, 16, comment="CRC-16/CCITT of payload bytes 0-1 and 4-7 (frames_sent, last_frame)"),
        _u("last_frame", 32, 32, comment="frame counter of the last frame produced"),
    ),
    "The sensor's frame source is exhausted; a receiver counts the frames lost after its last one from last_frame. "
    "A payload whose check does not match is refused (a corrupted frame must not end a stream).",
)

#: Every single-frame message, in identifier order (the DBC lists them so).
CAN_MESSAGES: tuple[CanMessageDef, ...] = tuple(
    sorted(
        (COMMAND, ACK, STAGE_FLOAT, COMMIT_BIND, TIME_BASE, FRAME_HEADER, STAR, END_OF_STREAM, FRAME_END),
        key=lambda m: m.frame_id,
    )
)
MESSAGES_BY_ID: dict[int, CanMessageDef] = {m.frame_id: m for m in CAN_MESSAGES}


class CanDecodeError(ValueError):
    """A CAN frame that is not a valid instance of its message (wrong length, bad field)."""


# --------------------------------------------------------------------------------------------- bit packing
def pack(msg: CanMessageDef, raw: dict[str, np.ndarray | int]) -> np.ndarray:
    """Raw signal values (unsigned ints of their width; signed / float signals as their bit patterns) -> uint64
    payloads. Arrays broadcast; the result is a uint64 array (little-endian payload = ``.astype('<u8').tobytes()``)."""
    word = np.zeros(np.broadcast_shapes(*(np.shape(v) for v in raw.values())), dtype=np.uint64)
    for name, value in raw.items():
        sig = msg.signal(name)
        bits = np.asarray(value).astype(np.uint64) & np.uint64(sig.mask)
        word |= bits << np.uint64(sig.start)
    return word


def unpack(msg: CanMessageDef, words: np.ndarray, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """uint64 payloads -> raw signal values (uint64 arrays), for ``names`` (default: every signal)."""
    w = np.asarray(words, dtype=np.uint64)
    out = {}
    for name in names or tuple(s.name for s in msg.signals):
        sig = msg.signal(name)
        out[name] = (w >> np.uint64(sig.start)) & np.uint64(sig.mask)
    return out


def payload_words(payloads: bytes | bytearray | memoryview) -> np.ndarray:
    """Concatenated 8-byte payloads -> one little-endian uint64 per frame."""
    if len(payloads) % CAN_PAYLOAD_BYTES:
        raise CanDecodeError(f"{len(payloads)} bytes is not a whole number of 8-byte CAN payloads")
    return np.frombuffer(bytes(payloads), dtype="<u8").astype(np.uint64)


def word_bytes(words: np.ndarray) -> bytes:
    """Inverse of :func:`payload_words`."""
    return np.asarray(words, dtype=np.uint64).astype("<u8").tobytes()


def _one_word(data: bytes | bytearray, msg: CanMessageDef) -> int:
    if len(data) != msg.length:
        raise CanDecodeError(f"{msg.name} frame must have {msg.length} data bytes, got {len(data)}")
    return int.from_bytes(bytes(data), "little")


# ------------------------------------------------------------------------------------------- stream frames
def encode_stars(frame: CentroidFrame) -> np.ndarray:
    """STAR payloads (uint64, one per star) of a centroid frame. Raises EncodeError for a centroid outside
    ``[-512, 7680)`` px or a star number above 131071."""
    x = quantise_px(frame.x_px) + _XY_RAW_OFFSET
    y = quantise_px(frame.y_px) + _XY_RAW_OFFSET
    limit = 1 << STAR_XY_BITS
    if np.any((x < 0) | (x >= limit) | (y < 0) | (y >= limit)):
        raise EncodeError(
            f"centroid outside the CAN star range [{STAR_XY_OFFSET_PX:g}, "
            f"{STAR_XY_OFFSET_PX + limit / CENTROID_STEPS_PER_PX:g}) px"
        )
    star_id = np.asarray(frame.star_id, dtype=np.int64)
    if np.any((star_id < 0) | (star_id >= 1 << STAR_ID_BITS)):
        raise EncodeError(f"star number does not fit in {STAR_ID_BITS} bits")
    return pack(STAR, {"x_px": x, "y_px": y, "star_id": star_id, "frame_parity": int(frame.frame) & 1})


def decode_stars(words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """STAR payloads -> (star_id uint32, x_px float64, y_px float64, frame_parity uint8); positions exact on the
    2**-10 px grid, identical to ``protocol.messages.dequantise_px`` of the same steps."""
    raw = unpack(STAR, words)
    x = dequantise_px(raw["x_px"].astype(np.int64) - _XY_RAW_OFFSET)
    y = dequantise_px(raw["y_px"].astype(np.int64) - _XY_RAW_OFFSET)
    return raw["star_id"].astype(np.uint32), x, y, raw["frame_parity"].astype(np.uint8)


def encode_header(frame: int, n_stars: int, t_offset_us: int) -> bytes:
    if not 0 <= n_stars <= MAX_STARS:
        raise EncodeError(f"{n_stars} stars exceed MAX_STARS={MAX_STARS}")
    if not 0 <= t_offset_us < 1 << TIME_OFFSET_BITS:
        raise EncodeError(f"time offset {t_offset_us} us does not fit in {TIME_OFFSET_BITS} bits")
    if not 0 <= frame < 1 << 32:
        raise EncodeError(f"frame={frame} does not fit in uint32")
    return word_bytes(pack(FRAME_HEADER, {"frame": frame, "n_stars": n_stars, "t_offset_us": t_offset_us}))


def decode_header(data: bytes | bytearray) -> tuple[int, int, int]:
    """FRAME_HEADER payload -> (frame, n_stars, t_offset_us)."""
    raw = unpack(FRAME_HEADER, np.uint64(_one_word(data, FRAME_HEADER)))
    return int(raw["frame"]), int(raw["n_stars"]), int(raw["t_offset_us"])


def encode_time_base(t_base_us: int) -> bytes:
    return int(t_base_us).to_bytes(8, "little", signed=True)


def decode_time_base(data: bytes | bytearray) -> int:
    _one_word(data, TIME_BASE)
    return int.from_bytes(bytes(data), "little", signed=True)


def _end_check(payload: bytes) -> int:
    return crc16_ccitt(payload[0:2] + payload[4:8])


def encode_end_of_stream(frames_sent: int, last_frame: int) -> bytes:
    """END_OF_STREAM payload (``frames_sent`` is sent modulo 65536)."""
    raw = {"frames_sent": int(frames_sent) & 0xFFFF, "last_frame": last_frame}
    payload = word_bytes(pack(END_OF_STREAM, raw))
    return word_bytes(pack(END_OF_STREAM, {**raw, "check": _end_check(payload)}))


def decode_end_of_stream(data: bytes | bytearray) -> tuple[int, int]:
    """END_OF_STREAM payload -> (frames_sent modulo 65536, last_frame); CanDecodeError if its check fails."""
    raw = unpack(END_OF_STREAM, np.uint64(_one_word(data, END_OF_STREAM)))
    if int(raw["check"]) != _end_check(bytes(data)):
        raise CanDecodeError("END_OF_STREAM check does not match")
    return int(raw["frames_sent"]), int(raw["last_frame"])


def frame_check(t_us: int, header: bytes | bytearray, stars: bytes | bytearray) -> int:
    """CRC-32 (``protocol.crc.crc32``) of the exposure time (int64 little-endian, us), the FRAME_HEADER payload and
    the concatenated STAR payloads: the ``frame_crc32`` of FRAME_END."""
    return crc32(int(t_us).to_bytes(8, "little", signed=True) + bytes(header) + bytes(stars))


def encode_frame_end(frame: int, frame_crc32: int) -> bytes:
    return word_bytes(pack(FRAME_END, {"frame_crc32": frame_crc32, "frame": frame}))


def decode_frame_end(data: bytes | bytearray) -> tuple[int, int]:
    """FRAME_END payload -> (frame, frame_crc32)."""
    raw = unpack(FRAME_END, np.uint64(_one_word(data, FRAME_END)))
    return int(raw["frame"]), int(raw["frame_crc32"])


def encode_stream_frame(
    frame: CentroidFrame, t_base_us: int | None, force_time_base: bool = False
) -> tuple[list[tuple[int, bytes]], int]:
    """The CAN frames (identifier, payload) of one centroid frame: [TIME_BASE,] FRAME_HEADER, STARs, FRAME_END; and
    the time base in force after them. A TIME_BASE goes first when ``force_time_base`` or the exposure time cannot be
    sent as an offset from ``t_base_us``. Raises EncodeError (before anything is produced) for a frame CAN cannot
    carry."""
    stars = word_bytes(encode_stars(frame))
    out: list[tuple[int, bytes]] = []
    if force_time_base or needs_time_base(frame.t_us, t_base_us):
        out.append((TIME_BASE.frame_id, encode_time_base(frame.t_us)))
        t_base_us = int(frame.t_us)
    header = encode_header(frame.frame, frame.n_stars, int(frame.t_us) - int(t_base_us))
    out.append((FRAME_HEADER.frame_id, header))
    out += [(STAR.frame_id, stars[i : i + CAN_PAYLOAD_BYTES]) for i in range(0, len(stars), CAN_PAYLOAD_BYTES)]
    out.append((FRAME_END.frame_id, encode_frame_end(frame.frame, frame_check(frame.t_us, header, stars))))
    return out, int(t_base_us)


class StreamEncoder:
    """The sensor's side of the CAN stream, one centroid frame at a time (:func:`encode_stream_frame`), with the time
    base policy: a TIME_BASE when the stream (re)starts (:meth:`restart`), when an offset would not fit, and after
    every TIME_BASE_EVERY_FRAMES frames. Pure state, no I/O."""

    def __init__(self) -> None:
        self.restart()

    def restart(self) -> None:
        self.t_base_us: int | None = None
        self._frames_since_base = 0

    def encode(self, frame: CentroidFrame) -> list[tuple[int, bytes]]:
        """CAN frames (identifier, payload) of ``frame``; EncodeError (and no state change) if CAN cannot carry it."""
        refresh = self._frames_since_base >= TIME_BASE_EVERY_FRAMES
        out, t_base = encode_stream_frame(frame, self.t_base_us, refresh)
        self._frames_since_base = 1 if out[0][0] == TIME_BASE.frame_id else self._frames_since_base + 1
        self.t_base_us = t_base
        return out


def needs_time_base(t_us: int, t_base_us: int | None) -> bool:
    """True when ``t_us`` cannot be sent as an offset from ``t_base_us`` (none yet, earlier, or too far)."""
    return t_base_us is None or not 0 <= t_us - t_base_us < 1 << TIME_OFFSET_BITS


# ------------------------------------------------------------------------------- short commands and ACK
_COMMAND_ARG = {StreamControl: "enable", StageBegin: "length", StageVerify: "verify_crc32", Commit: "commit_crc32"}
_COMMAND_CLASS = {
    cls.TYPE: cls
    for cls in (GetStatus, StreamControl, StageBegin, StageVerify, ReadStaged, Commit, ReadActive, ReadEstimate)
}
_ARG_ATTR = {StreamControl: "enable", StageBegin: "length", StageVerify: "crc32", Commit: "crc32"}


def is_single_frame(msg: Message) -> bool:
    """True for the messages that travel as one plain CAN frame (COMMAND, ACK). A COMMIT bound to a staging session
    (nonce or expected generation set) does not fit: it travels by ISO-TP."""
    if isinstance(msg, Commit) and (msg.nonce or msg.expected_generation):
        return False
    return type(msg) in _COMMAND_CLASS.values() or isinstance(msg, Ack)


def encode_single(msg: Message) -> tuple[int, bytes]:
    """(identifier, 8 data bytes) of a short command or an ACK (see :func:`is_single_frame`)."""
    if isinstance(msg, Ack):
        return ACK.frame_id, word_bytes(
            pack(ACK, {"type": int(MsgType.ACK), "tag": msg.tag, "command": msg.command, "value": msg.value})
        )
    cls = type(msg)
    if not is_single_frame(msg):
        raise EncodeError(f"{cls.__name__} is not a single-frame CAN message")
    raw = {"type": int(msg.TYPE), "tag": msg.tag}
    if cls in _COMMAND_ARG:
        raw[_COMMAND_ARG[cls]] = int(getattr(msg, _ARG_ATTR[cls]))
    return COMMAND.frame_id, word_bytes(pack(COMMAND, raw))


def decode_single(frame_id: int, data: bytes | bytearray) -> Message:
    """A COMMAND, STAGE_FLOAT or ACK frame -> its protocol message (STAGE_FLOAT -> StageChunk of 4 bytes)."""
    if frame_id == ACK.frame_id:
        raw = unpack(ACK, np.uint64(_one_word(data, ACK)))
        if int(raw["type"]) != MsgType.ACK:
            raise CanDecodeError(f"ACK frame with type byte 0x{int(raw['type']):02x}")
        return Ack(tag=int(raw["tag"]), command=int(raw["command"]), value=int(raw["value"]))
    if frame_id == STAGE_FLOAT.frame_id:
        raw = unpack(STAGE_FLOAT, np.uint64(_one_word(data, STAGE_FLOAT)))
        index = int(raw["field"])
        if index >= len(PARAM_FIELDS):
            raise CanDecodeError(f"STAGE_FLOAT field {index} is not a parameter (0..{len(PARAM_FIELDS) - 1})")
        value_bytes = int(raw["value"]).to_bytes(4, "little")
        return StageChunk(tag=int(raw["tag"]), offset=4 * index, data=value_bytes)
    if frame_id != COMMAND.frame_id:
        raise CanDecodeError(f"0x{frame_id:03X} is not a single-frame command or reply")
    raw = unpack(COMMAND, np.uint64(_one_word(data, COMMAND)))
    try:
        cls = _COMMAND_CLASS[MsgType(int(raw["type"]))]
    except (ValueError, KeyError):
        raise CanDecodeError(f"COMMAND frame with type 0x{int(raw['type']):02x} is not a short command") from None
    kwargs: dict[str, object] = {"tag": int(raw["tag"])}
    if cls in _COMMAND_ARG:
        value = int(raw[_COMMAND_ARG[cls]])
        kwargs[_ARG_ATTR[cls]] = bool(value) if cls is StreamControl else value
    return cls(**kwargs)


def encode_commit_bind(nonce: int, expected_generation: int) -> bytes:
    """COMMIT_BIND payload (sent immediately before a COMMAND COMMIT frame by a single-frame tool)."""
    return word_bytes(pack(COMMIT_BIND, {"nonce": nonce, "expected_generation": expected_generation}))


def bind_commit(commit: Commit, bind_payload: bytes | bytearray | None) -> Commit:
    """The COMMIT of a COMMAND frame joined with the COMMIT_BIND payload received just before it (None: unbound,
    nonce 0, which the sensor refuses)."""
    if bind_payload is None:
        return commit
    raw = unpack(COMMIT_BIND, np.uint64(_one_word(bind_payload, COMMIT_BIND)))
    return Commit(
        tag=commit.tag,
        crc32=commit.crc32,
        nonce=int(raw["nonce"]),
        expected_generation=int(raw["expected_generation"]),
    )


def encode_stage_float(tag: int, field_index: int, value: float) -> bytes:
    """STAGE_FLOAT payload staging ``value`` (rounded to float32) as field ``field_index`` of the table."""
    bits = int(np.array([value], dtype="<f4").view("<u4")[0])
    return word_bytes(pack(STAGE_FLOAT, {"tag": tag, "field": field_index, "value": bits}))


if TABLE_BYTES != 4 * len(PARAM_FIELDS):  # pragma: no cover - STAGE_FLOAT addresses the table one float32 per field
    raise ImportError("protocol.param_table is no longer one float32 per field; revise STAGE_FLOAT")


# ---------------------------------------------------------------------------------------------- the DBC
def _fmt(value: float) -> str:
    """A number as the DBC writes it: integers without a point, others with up to 17 significant digits."""
    v = float(value)
    return str(int(v)) if v.is_integer() and abs(v) < 1e15 else repr(v)


def _signal_line(sig: CanSignal, receivers: tuple[str, ...]) -> str:
    mux = " M" if sig.is_multiplexer else (f" m{sig.mux}" if sig.mux is not None else "")
    sign = "-" if sig.signed else "+"
    return (
        f" SG_ {sig.name}{mux} : {sig.start}|{sig.length}@1{sign} ({_fmt(sig.factor)},{_fmt(sig.offset)}) "
        f'[{_fmt(sig.minimum)}|{_fmt(sig.maximum)}] "{sig.unit}" {",".join(receivers)}'
    )


def dbc_text() -> str:
    """The DBC file describing every single-frame CAN message (checked in as ``protocol/startracker.dbc``)."""
    lines = [
        'VERSION "startracker-companion can_frames 1"',
        "",
        "NS_ :",
        "",
        "BS_:",
        "",
        f"BU_: {HOST} {SENSOR}",
        "",
    ]
    for msg in CAN_MESSAGES:
        lines.append(f"BO_ {msg.frame_id} {msg.name}: {msg.length} {msg.sender}")
        lines += [_signal_line(sig, msg.receivers) for sig in msg.signals]
        lines.append("")
    lines.append(
        'CM_ "Star sensor companion: single-frame CAN messages (generated by protocol.can_frames.dbc_text; '
        'ISO-TP on 0x0C0/0x0C1 carries the longer messages of protocol.messages)";'
    )
    for msg in CAN_MESSAGES:
        if msg.comment:
            lines.append(f'CM_ BO_ {msg.frame_id} "{msg.comment}";')
        for sig in msg.signals:
            if sig.comment:
                lines.append(f'CM_ SG_ {msg.frame_id} {sig.name} "{sig.comment}";')
    for msg in CAN_MESSAGES:
        for sig in msg.signals:
            if sig.choices:
                values = " ".join(f'{v} "{label}"' for v, label in sig.choices)
                lines.append(f"VAL_ {msg.frame_id} {sig.name} {values} ;")
    for msg in CAN_MESSAGES:
        for sig in msg.signals:
            if sig.is_float:
                lines.append(f"SIG_VALTYPE_ {msg.frame_id} {sig.name} : 1;")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover - regenerates protocol/startracker.dbc
    print(dbc_text(), end="")
