"""Serial link: protocol messages in COBS frames with CRC-32 and sequence numbers (``protocol.framing``) over any
port pyserial's ``serial_for_url`` opens (a UART, a pty, ``rfc2217://``, ``socket://``, ``loop://``).

Link string: ``serial:PORT_OR_URL[@BAUD]`` (default 921600 baud), e.g. ``serial:/dev/ttyUSB0@115200``,
``serial:/dev/pts/7@921600`` (what ``hostlink emulate --transport serial`` prints), ``serial:rfc2217://host:4000``.
Lost stream messages are counted from gaps in the sensor's sequence numbers, which number its stream messages
(centroid frames, end of stream) apart from its replies, so a reply lost mid-stream (a timeout the host resends
after) is not taken for a lost frame; frames failing COBS or CRC are counted as corrupt and skipped (the receiver
resynchronises at the next 0x00).
"""

from __future__ import annotations

import time
from collections import deque

import serial

from hostlink.errors import LinkError, UserError
from hostlink.links.base import DEFAULT_TIMEOUT_S, MessageLink
from hostlink.links.urlhandler import refuse_file_writing_url
from protocol.framing import FrameSplitter, FramingError, decode_frame, encode_frame, seq_gap
from protocol.messages import CentroidFrame, DecodeError, EndOfStream, Message, decode, encode

try:  # pyserial's POSIX flush() raises termios.error (not an OSError) when the other end of a pty is gone
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - not POSIX
    _TermiosError = OSError

DEFAULT_BAUD = 921_600
#: Bytes per STAGE_CHUNK on serial (a table goes in two chunks, so chunking is always exercised).
SERIAL_CHUNK_BYTES = 32
#: Longest a single blocking read waits before the deadline is re-checked [s].
_READ_SLICE_S = 0.05


def parse_target(target: str) -> tuple[str, int]:
    """``"/dev/ttyUSB0@115200"`` -> ``("/dev/ttyUSB0", 115200)``; the baud part is optional."""
    url, sep, baud_text = target.rpartition("@")
    if not sep or not baud_text.isdigit():
        url, baud_text = target, str(DEFAULT_BAUD)
    baud = int(baud_text)
    if not url or baud <= 0:
        raise UserError(f"--link serial:{target}: expected serial:PORT[@BAUD], e.g. serial:/dev/ttyUSB0@921600")
    return url, baud


class SerialLink(MessageLink):
    max_chunk_bytes = SERIAL_CHUNK_BYTES

    def __init__(self, port: serial.SerialBase, name: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        super().__init__(timeout_s)
        self.name = name
        self._port = port
        self._splitter = FrameSplitter()
        #: decoded messages not yet delivered, each with the stream messages lost just before it (counted in the
        #: stats when it is delivered, so they hold the loss up to the message the caller has, whatever was read after)
        self._ready: deque[tuple[Message, int]] = deque()
        self._tx_seq = 0
        self._rx_seq: int | None = None

    # ------------------------------------------------------------------------------------------ transport hooks
    def _send(self, msg: Message) -> None:
        data = encode_frame(self._tx_seq, encode(msg))
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError, _TermiosError) as exc:
            raise LinkError(f"{self.name}: write failed ({_reason(exc)})") from None
        self.stats.tx_bytes += len(data)

    def _receive(self, timeout_s: float) -> Message | None:
        deadline = time.monotonic() + timeout_s
        while not self._ready:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._read_some()
        msg, lost_before = self._ready.popleft()
        self.stats.lost_messages += lost_before
        return msg

    def _read_some(self) -> None:
        # the port's timeout is _READ_SLICE_S (set once: changing it reconfigures a POSIX port every call)
        try:
            data = self._port.read(max(1, self._port.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"{self.name}: connection lost ({_reason(exc)})") from None
        if not data:
            return
        self.stats.rx_bytes += len(data)
        for raw in self._splitter.feed(data):
            try:
                frame = decode_frame(raw)
                msg = decode(frame.payload)
            except (FramingError, DecodeError):
                self.stats.corrupt_frames += 1
                continue
            lost_before = 0
            if isinstance(msg, (CentroidFrame, EndOfStream)):
                # stream messages have their own sequence (replies are numbered apart), from 0 at the stream's
                # start: the frames lost before the first one received are counted too
                if self._rx_seq is not None:
                    lost_before = seq_gap(self._rx_seq, frame.seq)
                self._rx_seq = frame.seq
            self.stats.rx_messages += 1
            self._heard()
            self._ready.append((msg, lost_before))

    def _discard_input(self) -> None:
        try:
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"{self.name}: connection lost ({_reason(exc)})") from None
        self._splitter = FrameSplitter()
        self._ready.clear()

    def _reset_loss_counting(self) -> None:
        self._rx_seq = 0xFFFF  # the number before the new stream's first message, 0

    def close(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass


def _reason(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def open_link(scheme: str, target: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> SerialLink:
    """Open ``serial:TARGET`` (see the module docstring)."""
    url, baud = parse_target(target)
    refuse_file_writing_url(url, f"--link {scheme}:{target}:")
    try:
        port = serial.serial_for_url(url, baudrate=baud, timeout=_READ_SLICE_S, write_timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise LinkError(f"serial:{target}: cannot open ({_reason(exc)})") from None
    return SerialLink(port, f"{scheme}:{target}", timeout_s)
