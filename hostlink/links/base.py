"""The one ``Link`` interface every transport implements (serial, CAN, Modbus), like python-can's ``BusABC``.

The rest of the host (``hostlink.links.operations`` and the commands) only ever holds a :class:`Link`. Its operations
are the sensor's commands, one method each, so they can be carried by request/response messages (serial, CAN:
subclass :class:`MessageLink` and implement only ``_send`` / ``_receive``) or by registers (Modbus: subclass
:class:`Link` and implement each operation with register reads/writes). Whatever the transport, the sensor firmware
(``onboard.firmware``) decides every command: a link only carries it, so the safety rules are the same everywhere.

Contract of every operation (see hostlink/links/INTERFACE.md):

* returns only after the sensor answered; a refusal raises :class:`CommandRefused` (a ``SensorRefused``) with the
  sensor's :class:`~protocol.messages.NakCode` and one-line reason;
* no answer within ``timeout_s``, a closed port, or an answer that makes no sense raises
  :class:`~hostlink.errors.LinkError` with a one-line message (the CLI prints it and exits non-zero);
* values are the protocol's (``protocol.messages``): a parameter set is the 92-byte table of
  ``protocol.param_table``; frames are :class:`~protocol.messages.CentroidFrame`.
"""

from __future__ import annotations

import itertools
import random
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass

from hostlink.errors import LinkError, SensorRefused
from protocol.messages import (
    Ack,
    CentroidFrame,
    Commit,
    EndOfStream,
    Estimate,
    GetStatus,
    Message,
    MsgType,
    Nak,
    NakCode,
    ParamTable,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    Telemetry,
)

#: Default time to wait for the sensor's answer to one command [s].
DEFAULT_TIMEOUT_S = 2.0
#: Commands that may be sent again (same tag) when their reply is lost on a noisy line: doing them twice is doing
#: them once. Never COMMIT or STAGE_BEGIN (a second one would be refused as stale, or open a new staging session).
IDEMPOTENT_COMMANDS = (GetStatus, StreamControl, StageChunk, StageVerify, ReadStaged, ReadActive, ReadEstimate)
#: Sends of an idempotent command within one timeout (the first and the repeats, evenly spaced: every 125 ms at the
#: default 2 s). On a line losing 1 % of its bytes a 30-byte reply frame is lost with probability 0.26 and a 110-byte
#: parameter table with 0.67: 16 sends all fail with 4e-10 and 2e-3 (2 sends: 0.07 and 0.45). 125 ms is several
#: times a reply's round trip on the slowest line supported (115200 baud: a table reply takes 10 ms, behind at most
#: one 250-byte stream frame, 22 ms), so a slow reply is seldom asked for twice, and a duplicate is dropped by its tag.
COMMAND_SENDS = 16


class NoReply(LinkError):
    """No reply to a command within the link's timeout (the command or its reply lost, or the sensor gone)."""


class CommandRefused(SensorRefused):
    """The sensor answered a command with NAK: ``code`` (NakCode), ``text`` (its one-line reason)."""

    def __init__(self, command: int, code: int, text: str) -> None:
        self.command = int(command)
        self.code = int(code)
        self.text = text
        try:
            cmd_name = MsgType(command).name
        except ValueError:
            cmd_name = f"0x{command:02x}"
        try:
            code_name = NakCode(code).name
        except ValueError:
            code_name = f"code {code}"
        super().__init__(
            f"sensor refused {cmd_name}: {code_name}: {text}" if text else f"sensor refused {cmd_name}: {code_name}"
        )


@dataclass
class LinkStats:
    """Counters a link keeps while it is open (the stream command reports them)."""

    rx_messages: int = 0
    #: Messages the sensor sent that never arrived, counted from sequence-number gaps (0 where a transport has none),
    #: up to the last stream message delivered to the caller (not to what the link has read beyond it).
    lost_messages: int = 0
    #: Frames dropped on arrival (bad CRC, bad framing, undecodable).
    corrupt_frames: int = 0
    rx_bytes: int = 0
    tx_bytes: int = 0


class Link(ABC):
    """A connection to one sensor (real or emulated). Use as a context manager, or call :meth:`close`."""

    #: The link string it was opened with (``--link``).
    name: str = ""
    #: Largest ``data`` a single :meth:`stage_chunk` carries on this transport [bytes].
    max_chunk_bytes: int = 32

    def __init__(self) -> None:
        self.stats = LinkStats()

    # ------------------------------------------------------------------------------------- commands
    @abstractmethod
    def status(self) -> Telemetry:
        """The sensor's status (stream on/off, staging state, active generation and CRC, counters)."""

    @abstractmethod
    def set_streaming(self, enable: bool) -> None:
        """Start or stop the centroid stream. ``set_streaming(True)`` starts a new stream (stopping one left running
        first): :meth:`recv_frame` then yields only frames of this stream, and :attr:`stats` count the stream's
        messages lost from its start (frames lost before the first one received included) and its corrupt ones."""

    @abstractmethod
    def stage_begin(self, length: int) -> int:
        """Safe upload step 2a: clear the staging area for a table of ``length`` bytes; returns the new staging
        session's nonce, which :meth:`commit` must carry."""

    @abstractmethod
    def stage_chunk(self, offset: int, data: bytes) -> None:
        """Safe upload step 2b: write ``data`` (at most :attr:`max_chunk_bytes`) at byte ``offset`` of the table."""

    @abstractmethod
    def stage_verify(self, crc32: int) -> None:
        """Safe upload step 3: the sensor checks the staged set against ``crc32`` and its ranges (NAK BAD_CRC,
        INVALID_PARAMS with the field and reason, ...)."""

    @abstractmethod
    def read_staged(self) -> ParamTable:
        """Safe upload step 4: the staged set as the sensor holds it (``bank = STAGED``)."""

    @abstractmethod
    def commit(self, crc32: int, nonce: int = 0, expected_generation: int = 0) -> int:
        """Safe upload step 5: the sensor writes the verified staged set (CRC ``crc32``) into its inactive bank with
        the next generation number and switches atomically, only if ``nonce`` is the current staging session's
        (:meth:`stage_begin`'s answer) and ``expected_generation`` the active one (else NAK STALE_SESSION). Returns
        the new generation."""

    @abstractmethod
    def read_active(self) -> ParamTable:
        """Safe upload step 6 (and ``hostlink params``): the active set with its generation and CRC."""

    @abstractmethod
    def read_estimate(self) -> Estimate:
        """The onboard recursive estimate (NAK NO_ESTIMATE before the first update)."""

    # ---------------------------------------------------------------------------------------- stream
    @abstractmethod
    def recv_frame(self, timeout_s: float | None = None) -> CentroidFrame | None:
        """The next streamed centroid frame, or None once the sensor reported the end of its stream (a replay that
        ran out). Raises LinkError when nothing arrives within ``timeout_s`` (default: the link's timeout)."""

    # ------------------------------------------------------------------------------------- lifecycle
    @abstractmethod
    def close(self) -> None:
        """Release the port / bus / socket. Idempotent."""

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class MessageLink(Link):
    """A :class:`Link` over a transport that carries whole protocol messages (serial frames, ISO-TP on CAN).

    Subclasses implement :meth:`_send` and :meth:`_receive`, and count losses in :attr:`stats`; everything else
    (tags, matching replies, queueing stream messages that arrive while waiting for a reply, NAK -> exception,
    timeouts) is done here once.
    """

    def __init__(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        super().__init__()
        self.timeout_s = float(timeout_s)
        # tags start at a random value, so a stale reply left on the line by an earlier host process (or another
        # host on a shared CAN bus) is not taken for the answer to this link's first commands
        first_tag = random.SystemRandom().randrange(1, 1 << 16)
        self._tags = itertools.cycle([*range(first_tag, 1 << 16), *range(1, first_tag)])
        self._stream: deque[CentroidFrame | EndOfStream] = deque()
        self._ended = False
        #: when the sensor was last heard (an intact frame of any kind, :meth:`_heard`): a stream on a noisy line
        #: goes on while the sensor is heard, even when no whole centroid frame arrives within the timeout
        self._heard_at = 0.0

    # ---------------------------------------------------------------------- transport hooks (abstract)
    @abstractmethod
    def _send(self, msg: Message) -> None:
        """Put one message on the wire. Raise LinkError if the transport is gone."""

    @abstractmethod
    def _receive(self, timeout_s: float) -> Message | None:
        """The next message that arrived intact, or None if none arrived within ``timeout_s``. Corrupt frames are
        counted in :attr:`stats` and skipped, never returned. Raise LinkError if the transport is gone (EOF)."""

    def _heard(self) -> None:
        """Subclasses call it for every intact frame received from the sensor (CRC or bus check passed)."""
        self._heard_at = time.monotonic()

    def _discard_input(self) -> None:  # noqa: B027 - optional hook
        """Drop bytes already received but not yet read (called before a stream starts). Optional."""

    def _reset_loss_counting(self) -> None:  # noqa: B027 - optional hook
        """Forget the last sequence number seen, so the next message does not count as a gap. Optional."""

    # -------------------------------------------------------------------------------- request/reply
    def request(self, command: Message, expect: type, *, fresh_tags: bool = False) -> Message:
        """Send ``command`` with a fresh tag and return the reply of type ``expect`` that echoes the tag.
        Stream messages arriving meanwhile are queued for :meth:`recv_frame`; stale replies are dropped.
        Idempotent commands are sent again with the same tag while no reply comes; ``fresh_tags``: sent again too,
        each time as a new command with a new tag, only the reply to the latest counting (STAGE_BEGIN: each one
        opens a new staging session and voids the earlier ones). NoReply after the link's timeout."""
        tag = next(self._tags)
        command = type(command)(**{**command.__dict__, "tag": tag})
        self._send(command)
        start = time.monotonic()
        deadline = start + self.timeout_s
        sends = COMMAND_SENDS if isinstance(command, IDEMPOTENT_COMMANDS) or fresh_tags else 1
        next_send = start + self.timeout_s / sends
        while True:
            now = time.monotonic()
            remaining = deadline - now
            if remaining <= 0:
                raise NoReply(f"{self.name}: no reply to {command.TYPE.name} within {self.timeout_s:g} s")
            if sends > 1 and now >= next_send:  # the command or its reply was lost: send it again
                if fresh_tags:
                    tag = next(self._tags)
                    command = type(command)(**{**command.__dict__, "tag": tag})
                self._send(command)
                next_send += self.timeout_s / sends
            msg = self._receive(min(remaining, max(0.0, next_send - now)) if sends > 1 else remaining)
            if msg is None:
                continue
            if isinstance(msg, (CentroidFrame, EndOfStream)):
                self._stream.append(msg)
                continue
            if getattr(msg, "tag", None) != tag:
                continue  # a late reply to an earlier command that timed out
            if isinstance(msg, Nak):
                raise CommandRefused(msg.command, msg.code, msg.text)
            if not isinstance(msg, expect) or (isinstance(msg, Ack) and msg.command != command.TYPE):
                raise LinkError(f"{self.name}: sensor answered {command.TYPE.name} with {type(msg).__name__}")
            return msg

    # ---------------------------------------------------------------------------------- operations
    def status(self) -> Telemetry:
        return self.request(GetStatus(), Telemetry)

    def set_streaming(self, enable: bool) -> None:
        if enable:
            # A stream is counted from its start: a stream left running (by an earlier host) is stopped first, so
            # that the enable starts a new one, whose messages the sensor numbers afresh and whose ACK carries its
            # first frame counter. Loss counting restarts before the enable goes out: the sensor may start sending
            # the moment it acknowledges, and frames that arrive before the ACK (a lost ACK, the enable sent again)
            # belong to the new stream.
            self.request(StreamControl(enable=False), Ack)
            self._discard_input()
            self._stream.clear()
            self._reset_loss_counting()
            self.stats.lost_messages = 0
            self.stats.corrupt_frames = 0
        ack = self.request(StreamControl(enable=enable), Ack)
        if enable:
            self._stream_started(int(ack.value))
        else:
            self._stream.clear()
        self._ended = False

    def _stream_started(self, first_frame: int) -> None:  # noqa: B027 - optional hook
        """The sensor acknowledged a new stream whose first exposure has frame counter ``first_frame`` (low 32 bits).
        Optional: a transport that numbers stream messages from the stream's start (serial) needs nothing more."""

    def stage_begin(self, length: int) -> int:
        return int(self.request(StageBegin(length=length), Ack, fresh_tags=True).value)

    def stage_chunk(self, offset: int, data: bytes) -> None:
        self.request(StageChunk(offset=offset, data=bytes(data)), Ack)

    def stage_verify(self, crc32: int) -> None:
        self.request(StageVerify(crc32=crc32), Ack)

    def read_staged(self) -> ParamTable:
        return self.request(ReadStaged(), ParamTable)

    def commit(self, crc32: int, nonce: int = 0, expected_generation: int = 0) -> int:
        """COMMIT is sent once (a second one could never match: the first voids the session). When no reply comes,
        the active set says whether it ran (the next generation with this CRC: done, its reply was lost); if not,
        the staging session is still live and COMMIT is sent once more."""
        command = Commit(crc32=crc32, nonce=nonce, expected_generation=expected_generation)
        try:
            return int(self.request(command, Ack).value)
        except NoReply:
            pass
        active = self.read_active()
        if active.generation == expected_generation + 1 and active.crc32 == crc32:
            return int(active.generation)
        return int(self.request(command, Ack).value)

    def read_active(self) -> ParamTable:
        return self.request(ReadActive(), ParamTable)

    def read_estimate(self) -> Estimate:
        return self.request(ReadEstimate(), Estimate)

    def recv_frame(self, timeout_s: float | None = None) -> CentroidFrame | None:
        """The next frame; LinkError when neither a frame nor anything intact from the sensor arrived within
        ``timeout_s`` (a noisy line may lose every whole frame for a while; the sensor is still there)."""
        timeout_s = self.timeout_s if timeout_s is None else float(timeout_s)
        start = time.monotonic()
        while True:
            if self._stream:
                msg = self._stream.popleft()
                if isinstance(msg, EndOfStream):
                    self._ended = True
                    return None
                return msg
            if self._ended:
                return None
            remaining = max(start, self._heard_at) + timeout_s - time.monotonic()
            if remaining <= 0:
                raise LinkError(
                    f"{self.name}: no centroid frame within {timeout_s:g} s (nor anything intact from the sensor)"
                )
            msg = self._receive(remaining)
            if isinstance(msg, (CentroidFrame, EndOfStream)):
                self._stream.append(msg)
