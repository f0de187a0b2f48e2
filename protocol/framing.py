"""Serial framing (byte streams: UART, pty, TCP serial bridges): COBS, a CRC per frame, and a sequence number.

One frame on the wire::

    COBS( seq:u16 LE | payload | crc32:u32 LE ) 0x00

* ``payload`` is one message as encoded by :func:`protocol.messages.encode` (type byte first).
* ``crc32`` (:func:`protocol.crc.crc32`) covers ``seq`` and ``payload``.
* ``seq`` counts frames per direction, modulo 2**16; a receiver counts lost frames from the gaps.
* COBS (Cheshire & Baker 1999) removes every 0x00 from the frame, so 0x00 delimits frames and a receiver
  resynchronises at the next delimiter after any corruption. Overhead: 1 byte per started 254 bytes, plus the
  delimiter.

Pure functions: bytes in, frames out; :class:`FrameSplitter` only buffers the bytes of a partial frame.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from cobs import cobs

from protocol.crc import crc32

DELIMITER = b"\x00"
SEQ_MODULUS = 1 << 16
_SEQ = struct.Struct("<H")
_CRC = struct.Struct("<I")
#: Bytes of the sequence number (first, little-endian) and of the CRC-32 (last, little-endian) of a frame.
SEQ_BYTES = _SEQ.size
CRC_BYTES = _CRC.size
#: Bytes a frame adds to its payload before COBS: sequence number and CRC.
FRAME_FIELDS_BYTES = SEQ_BYTES + CRC_BYTES


class FramingError(ValueError):
    """A frame that cannot be trusted (bad COBS, bad CRC, too short)."""


@dataclass(frozen=True)
class SerialFrame:
    seq: int
    payload: bytes


def encode_frame(seq: int, payload: bytes) -> bytes:
    """One delimited wire frame for ``payload`` with sequence number ``seq`` (taken modulo 2**16)."""
    body = _SEQ.pack(seq % SEQ_MODULUS) + payload
    return cobs.encode(body + _CRC.pack(crc32(body))) + DELIMITER


def decode_frame(encoded: bytes) -> SerialFrame:
    """Inverse of :func:`encode_frame` for one frame *without* its delimiter. Raises :class:`FramingError`."""
    try:
        raw = cobs.decode(encoded)
    except cobs.DecodeError as exc:
        raise FramingError(f"bad COBS encoding ({exc})") from None
    if len(raw) < FRAME_FIELDS_BYTES:
        raise FramingError(f"frame too short ({len(raw)} bytes)")
    body, (crc,) = raw[: -_CRC.size], _CRC.unpack_from(raw, len(raw) - _CRC.size)
    if crc32(body) != crc:
        raise FramingError("CRC mismatch")
    return SerialFrame(seq=_SEQ.unpack_from(body)[0], payload=bytes(body[_SEQ.size :]))


def framed_size(payload_bytes: int) -> int:
    """Bytes on the wire for a payload of ``payload_bytes``: COBS worst case (the exact size for payloads without
    zero bytes in a 254-byte run is the same), fields and delimiter. Used for line-rate pacing and link limits."""
    inner = payload_bytes + FRAME_FIELDS_BYTES
    return inner + (inner + 253) // 254 + len(DELIMITER)


def seq_gap(previous: int, current: int) -> int:
    """Frames lost between two consecutively received sequence numbers (0 when ``current`` follows ``previous``)."""
    return (current - previous - 1) % SEQ_MODULUS


class FrameSplitter:
    """Accumulates a byte stream and yields the complete (still COBS-encoded) frames between delimiters."""

    def __init__(self, max_frame_bytes: int = 1 << 16) -> None:
        self._buffer = bytearray()
        self._max = max_frame_bytes
        #: Bytes thrown away because a frame overflowed ``max_frame_bytes`` (a line without delimiters).
        self.discarded_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the complete frames now available (empty frames are skipped)."""
        self._buffer += data
        if DELIMITER not in data:
            if len(self._buffer) > self._max:
                self.discarded_bytes += len(self._buffer)
                self._buffer.clear()
            return []
        parts = bytes(self._buffer).split(DELIMITER)
        rest = parts[-1]
        if len(rest) > self._max:
            self.discarded_bytes += len(rest)
            rest = b""
        self._buffer = bytearray(rest)
        out = []
        for p in parts[:-1]:
            if len(p) > self._max:  # the limit holds whether or not the read also held a delimiter
                self.discarded_bytes += len(p)
            elif p:
                out.append(p)
        return out
