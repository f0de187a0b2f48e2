"""CAN link: any python-can interface; short commands and ACKs as single frames, the rest by ISO-TP (can-isotp),
the centroid stream as one frame per star (``protocol.can_frames``).

Link string: ``can:INTERFACE:CHANNEL[@BITRATE][,KEY=VALUE...]`` -- the python-can interface name, its channel, the
CAN bit rate in bit/s (default 500000; passed to python-can as ``bitrate``) and optional keyword arguments of that
interface (numbers are converted). Examples:

* ``can:slcan:socket://127.0.0.1:PORT@500000`` -- what ``hostlink emulate --transport can`` prints (an SLCAN adapter
  emulated over TCP by ``hostlink.emulator.slcan_hub``);
* ``can:slcan:/dev/ttyACM0@500000,tty_baudrate=115200`` -- a real SLCAN (CANable, Lawicel) adapter;
* ``can:socketcan:can0`` -- a Linux SocketCAN interface (the bit rate is set with ``ip link``, not here);
* ``can:pcan:PCAN_USBBUS1@250000``, ``can:kvaser:0@500000``, ``can:virtual:test`` -- any other python-can interface;
* ``can:config`` and ``can:config:CONTEXT`` -- the interface, channel and the rest from python-can's own
  configuration (environment, ``~/.canrc``; :func:`bus_config`), which also fills what any link string leaves out.

:func:`link_on_bus` runs a link on a ``can.BusABC`` the caller opened (``hostlink.api.open_link(bus)``).

The host node uses identifiers 0x0A0 (COMMAND), 0x0A2 (STAGE_FLOAT) and 0x0C0 (ISO-TP to the sensor); the sensor
0x0A1 (ACK), 0x0C1 (ISO-TP to the host) and 0x100-0x103 (stream). Loss is counted from gaps in the frame counter,
from frames whose stars did not all arrive, and from stars whose frame parity does not match their header.

Limits, by design of the CAN layout (``protocol/startracker.dbc``):

* FRAME_HEADER's 64 bits are all used (frame 32, n_stars 8, t_offset_us 24), so there is no link sequence number as
  on serial and Modbus: the frame counter is the sequence. A sensor numbers every exposure and sends every one (a
  frame without stars is a header with n_stars = 0), so a gap is a loss. An emulator replaying a session whose frame
  numbers are not consecutive (a session recorded with losses, or simulated with frames left out) therefore reports
  those gaps as lost messages on CAN only; the frames themselves arrive intact.
* One host node per bus: two hosts share the host identifiers, so each sees the other's replies (ignored by their
  tags, which start at a random value per link) and ISO-TP flow control; run one host command at a time.
"""

from __future__ import annotations

import gc
import logging
import math
import queue
import threading
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import can
import isotp
import numpy as np

from hostlink.errors import LinkError, UserError, one_line
from hostlink.links.base import DEFAULT_TIMEOUT_S, MessageLink
from hostlink.links.urlhandler import refuse_file_writing_url
from protocol import can_frames as cf
from protocol.messages import (
    Ack,
    CentroidFrame,
    DecodeError,
    EncodeError,
    EndOfStream,
    Message,
    StreamControl,
    decode,
    encode,
)
from protocol.param_table import TABLE_BYTES

DEFAULT_BITRATE = 500_000
# can-isotp logs protocol oddities (e.g. "Received a FlowControl message while transmission was Idle") as warnings,
# which Python prints on stderr without a handler: the link counts them in IsoTpChannel.errors and reports failures
# in one line itself (CLI contract).
logging.getLogger("isotp").setLevel(logging.CRITICAL)
#: ISO-TP settings on both nodes: no separation time and no block limit, so a long message streams back to back
#: (the bus, not the protocol, sets the pace); 1 s timeouts for a missing flow control or consecutive frame.
ISOTP_PARAMS: dict[str, object] = {
    "stmin": 0,
    "blocksize": 0,
    "tx_data_length": 8,
    "tx_padding": None,
    "max_frame_size": 4095,
    "rx_flowcontrol_timeout": 1000,
    "rx_consecutive_frame_timeout": 1000,
    "blocking_send": False,
}
#: Poll period of the reader thread while ISO-TP has work pending / while idle [s].
_POLL_BUSY_S = 0.001
_POLL_IDLE_S = 0.02


@dataclass(frozen=True)
class CanTarget:
    """A parsed ``can:`` link string. ``interface`` and ``channel`` empty: take them from python-can's configuration
    (``can:config[:CONTEXT]``); ``bitrate`` the string's, or the default where python-can's configuration gives
    none (``explicit_bitrate`` False); ``context`` the configuration section (python-can's ``config_context``)."""

    interface: str
    channel: str
    bitrate: int | None
    options: dict[str, object] = field(default_factory=dict)
    context: str | None = None
    explicit_bitrate: bool = field(default=True, compare=False)


#: ``can:config[:CONTEXT]``: the interface and channel (and anything else) from python-can's own configuration.
CONFIG_TARGET = "config"


def _option_value(text: str) -> object:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    return text


def parse_target(target: str) -> CanTarget:
    """``"slcan:socket://127.0.0.1:5000@500000,sleep_after_open=0"`` -> CanTarget. One-line UserError if malformed."""
    usage = (
        f"--link can:{target}: expected can:INTERFACE:CHANNEL[@BITRATE][,KEY=VALUE...], "
        "e.g. can:socketcan:can0 or can:slcan:socket://127.0.0.1:5000@500000"
    )
    main, *opts = str(target).split(",")
    if main.split("@")[0].split(":")[0].strip() == CONFIG_TARGET:
        return _config_target(main, opts, usage)
    interface, sep, rest = main.partition(":")
    if not sep or not interface or not rest:
        raise UserError(usage)
    channel, at, rate_text = rest.rpartition("@")
    bitrate: int | None = DEFAULT_BITRATE
    if not at or not rate_text.isdigit():
        channel = rest
    else:
        bitrate = int(rate_text)
        if bitrate <= 0:
            raise UserError(usage)
    options = _options(opts, usage)
    if interface == "socketcan" and not at:
        bitrate = None  # SocketCAN's bit rate belongs to the kernel interface (ip link set canX type can bitrate N)
    if not channel:
        raise UserError(usage)
    return CanTarget(interface.strip(), channel, bitrate, options, explicit_bitrate=bool(at))


def _options(opts: list[str], usage: str) -> dict[str, object]:
    options: dict[str, object] = {}
    for opt in opts:
        key, eq, value = opt.partition("=")
        if not eq or not key.strip():
            raise UserError(usage)
        options[key.strip()] = _option_value(value.strip())
    return options


def _config_target(main: str, opts: list[str], usage: str) -> CanTarget:
    """``config[:CONTEXT][@BITRATE]``: python-can's configuration (its ``default`` section, or ``CONTEXT``)."""
    head, at, rate_text = main.partition("@")
    _, _, context = head.partition(":")
    if at and not (rate_text.isdigit() and int(rate_text) > 0):
        raise UserError(usage)
    bitrate = int(rate_text) if at else DEFAULT_BITRATE
    return CanTarget("", "", bitrate, _options(opts, usage), context.strip() or None, explicit_bitrate=bool(at))


def bus_config(t: CanTarget) -> dict:
    """The keyword arguments of ``can.Bus`` for a target, resolved as python-can resolves them
    (``can.util.load_config``: the link string's values first, then ``can.rc``, the environment ``CAN_INTERFACE``,
    ``CAN_CHANNEL``, ``CAN_BITRATE``, ``CAN_CONFIG`` (with ``_CONTEXT`` suffixes), then the files ``~/.canrc``,
    ``~/.can``, ``/etc/can.conf``, section ``default`` or the target's context). The default bit rate only where
    neither the string nor the configuration gives one (and never for SocketCAN, whose rate the kernel sets). A
    configuration that names no usable interface is a one-line UserError."""
    given: dict[str, object] = {**t.options}
    if t.interface:
        given["interface"] = t.interface
    if t.channel:
        given["channel"] = t.channel
    if t.explicit_bitrate and t.bitrate is not None:
        given["bitrate"] = t.bitrate
    try:
        config = dict(can.util.load_config(config=given, context=t.context))
    except can.CanInterfaceNotImplementedError as exc:
        where = f" (context {t.context})" if t.context else ""
        if not t.interface:
            raise UserError(
                f"can:{CONFIG_TARGET}: python-can's configuration{where} names no usable interface ({one_line(exc)}); "
                "set CAN_INTERFACE and CAN_CHANNEL, or interface and channel in ~/.canrc"
            ) from None
        raise UserError(f"CAN interface {t.interface} is not available here ({one_line(exc)})") from None
    except (ValueError, TypeError) as exc:
        raise UserError(f"python-can's configuration: {one_line(exc)}") from None
    if config.get("channel") is None:
        raise UserError(
            f"can: no channel for interface {config['interface']} in the link string or python-can's "
            "configuration (CAN_CHANNEL, or channel in ~/.canrc)"
        )
    if config.get("bitrate") is None and config["interface"] != "socketcan" and t.bitrate is not None:
        config["bitrate"] = t.bitrate
    if config.get("bitrate") is None:
        config.pop("bitrate", None)
    return config


def open_bus(t: CanTarget) -> can.BusABC:
    """Open the python-can bus named by a target. One-line UserError when the interface is unknown or its driver is
    missing on this machine, LinkError when the bus cannot be opened."""
    kwargs = bus_config(t)
    interface, channel = kwargs.pop("interface"), str(kwargs.pop("channel"))
    t = replace(t, interface=interface, channel=channel)
    if "://" in channel:
        refuse_file_writing_url(channel, f"--link can:{interface}:")
    if interface == "slcan" and "://" in channel:
        kwargs.setdefault("sleep_after_open", 0)  # a network adapter needs no boot delay (a USB one does: 2 s)
        if channel.lower().startswith("socket://"):
            channel = _buffered_socket_url(channel)
    with _driver_log() as records:
        try:
            bus = can.Bus(interface=interface, channel=channel, ignore_config=True, **kwargs)
        except (can.CanInterfaceNotImplementedError, ImportError, NameError, AttributeError) as exc:
            # python-can raises the first for an unknown name or a driver it could not load; the others come from
            # interface modules that import without their vendor library and fail on first use (kvaser: NameError)
            said = [" ".join(r.getMessage().split()) for r in records if r.levelno >= logging.WARNING]
            reason = "; ".join(dict.fromkeys([*said, one_line(exc)]))[:300]
            error: UserError = UserError(f"CAN interface {t.interface} is not available here ({reason})")
        except (can.CanError, OSError, ValueError, TypeError) as exc:
            error = LinkError(f"cannot open CAN interface {t.interface} channel {t.channel}: {one_line(exc)}")
        else:
            error = None
        if error is not None:
            gc.collect()  # a half-built bus logs "... was not properly shut down" when collected: in here, not later
    if error is not None:
        raise error
    for record in records:  # an open that worked: what the driver logged goes on as usual
        logging.getLogger(record.name).handle(record)
    return bus


@contextmanager
def _driver_log() -> Iterator[list[logging.LogRecord]]:
    """Holds back what python-can and its interface modules log while a bus is opened (a missing vendor library is
    logged as a warning on import, besides the exception), so that a failed open is one line."""
    logger = logging.getLogger("can")
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.DEBUG)
    handler.emit = records.append  # type: ignore[method-assign]
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _buffered_socket_url(url: str) -> str:
    """``socket://H:P`` -> ``bufsocket://H:P``: the same socket through ``hostlink.links.urlhandler``'s buffered
    handler, so python-can's byte-at-a-time SLCAN reader keeps up with a 1 Mbit/s bus."""
    import serial

    if "hostlink.links.urlhandler" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("hostlink.links.urlhandler")
    return "bufsocket://" + url.split("://", 1)[1]


def open_link(scheme: str, target: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> CanLink:
    t = parse_target(target)
    return CanLink(open_bus(t), f"{scheme}:{target}", timeout_s)


def link_on_bus(bus: can.BusABC, timeout_s: float = DEFAULT_TIMEOUT_S) -> CanLink:
    """A sensor link on a python-can bus the caller already opened (any ``can.BusABC``). Closing the link stops its
    reader but leaves the bus open: whoever opened it shuts it down, as python-can's own users expect."""
    if not isinstance(bus, can.BusABC):
        raise UserError(f"expected a link string or an open python-can bus (can.BusABC), got {type(bus).__name__}")
    return CanLink(bus, f"can:{bus.channel_info}", timeout_s, owns_bus=False)


# --------------------------------------------------------------------------------------------- ISO-TP
class IsoTpChannel:
    """One ISO-TP endpoint (can-isotp's TransportLayer without its threads), driven by the owner's reader thread:
    :meth:`feed` gives it the received frames of its identifier, :meth:`poll` runs its state machines and returns the
    complete messages. :meth:`send` may be called from any thread."""

    def __init__(self, send_frame, txid: int, rxid: int) -> None:  # noqa: ANN001 - callable(can.Message)
        self._send_frame = send_frame
        self._rx: list[isotp.CanMessage] = []
        self._lock = threading.RLock()
        self.errors = 0
        self._stack = isotp.TransportLayer(
            rxfn=self._rxfn,
            txfn=self._txfn,
            address=isotp.Address(isotp.AddressingMode.Normal_11bits, txid=txid, rxid=rxid),
            error_handler=self._on_error,
            params=dict(ISOTP_PARAMS),
        )

    def _rxfn(self, timeout: float) -> isotp.CanMessage | None:  # noqa: ARG002 - never blocks
        return self._rx.pop(0) if self._rx else None

    def _txfn(self, msg: isotp.CanMessage) -> None:
        self._send_frame(can.Message(arbitration_id=msg.arbitration_id, data=msg.data, is_extended_id=False))

    def _on_error(self, error: Exception) -> None:
        self.errors += 1

    def feed(self, msg: can.Message) -> None:
        with self._lock:
            self._rx.append(
                isotp.CanMessage(arbitration_id=msg.arbitration_id, data=bytes(msg.data), extended_id=False)
            )

    def send(self, payload: bytes) -> None:
        with self._lock:
            self._stack.send(bytes(payload))
            self._stack.process(do_rx=False)

    def poll(self) -> list[bytes]:
        with self._lock:
            self._stack.process()
            out = []
            while self._stack.available():
                out.append(bytes(self._stack.recv()))
            return out

    def reset(self) -> None:
        """Back to idle: frames not yet processed and any partial message in either direction are dropped (as
        after a power cycle of the node; constructing a channel costs milliseconds in can-isotp's checks)."""
        with self._lock:
            self._rx.clear()
            self._stack.reset()

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._stack.transmitting() or bool(self._rx) or self._stack.rx_state != self._stack.RxState.IDLE


# --------------------------------------------------------------------------------------- stream decoding
class StreamAssembler:
    """Host-side decoding of the CAN centroid stream: TIME_BASE, FRAME_HEADER, STAR and FRAME_END frames ->
    CentroidFrame.

    A frame is delivered only when its FRAME_END arrives with the frame counter of its header and the CRC-32 of what
    was received (``protocol.can_frames.frame_check``: exposure time, header, stars). ``lost`` counts the frames the
    sensor sent that were not delivered, from the gaps between the counters of delivered frames (and, at
    END_OF_STREAM, after the last one): a rejected frame is a lost frame, counted once. ``corrupt`` counts the CAN
    frames and assembled frames that were refused (bad length, a star without a header, a FRAME_END that does not
    match its frame); ``incomplete``: frames refused because stars were missing or extra or their FRAME_END never
    came; ``refused_between``: frames refused (incomplete or corrupt) between two delivered frames, so
    ``lost - refused_between`` frames left no trace at all.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        self._start: int | None = None  # the stream's first frame counter, once the sensor told it (begin_at)
        self._awaiting_start = False  # a stream was started (forget_sequence) and its ACK has not come yet
        self.lost_at_start = 0  # frames lost up to the last one delivered before begin_at
        self._delivered: list[int] = []  # counters delivered since forget_sequence, until the start is known
        self.t_base_us: int | None = None
        self._frame: tuple[int, int, int, bytes] | None = None  # frame, n_stars, t_us, header payload
        self._stars = bytearray()
        self._last_frame: int | None = None
        self.lost = 0
        self.corrupt = 0
        self.incomplete = 0
        self.refused_between = 0
        self._refused_pending = 0  # refused since the last delivered frame

    def forget_sequence(self) -> None:
        """Start loss counting afresh (a new stream), keeping the time base."""
        with self._lock:
            self._frame, self._stars, self._last_frame = None, bytearray(), None
            self.lost = self.corrupt = self.incomplete = self.refused_between = self._refused_pending = 0
            self._start, self._delivered = None, []
            self._awaiting_start = True

    def begin_at(self, first_frame: int) -> None:
        """The stream began with frame counter ``first_frame`` (the ACK of STREAM_CONTROL enable): loss is counted
        from it, frames lost before the first one delivered included. Frames delivered before this call that
        precede it (a stream left running, stopped just before) are stale: they are not counted, and
        :meth:`is_stale` says so for the link to drop them. Idempotent for one stream (a repeated ACK)."""
        with self._lock:
            if self._start is not None:
                return
            self._start = first_frame % (1 << 32)
            fresh = [c for c in self._delivered if not self._precedes_start(c)]
            self._delivered, self._awaiting_start = [], False
            if fresh:
                self.lost = (fresh[-1] - self._start + 1) % (1 << 32) - len(fresh)
                self._last_frame = fresh[-1]
            else:
                self.lost = 0
                self._last_frame = (self._start - 1) % (1 << 32)
            self.lost_at_start = self.lost

    def _precedes_start(self, counter: int) -> bool:
        # counters are compared on the circle of 2**32: "before" is up to half of it behind
        return self._start is not None and (counter - self._start) % (1 << 32) >= 1 << 31

    def is_stale(self, frame: CentroidFrame) -> bool:
        """The frame precedes the stream's start (known from :meth:`begin_at`)."""
        with self._lock:
            return self._precedes_start(frame.frame)

    def feed(self, frame_id: int, data: bytes) -> CentroidFrame | EndOfStream | None:
        """One received stream frame; the completed message, if this frame completed one."""
        with self._lock:
            return self._feed(frame_id, data)

    def _feed(self, frame_id: int, data: bytes) -> CentroidFrame | EndOfStream | None:
        try:
            if frame_id == cf.STAR.frame_id:
                self._star(data)
            elif frame_id == cf.FRAME_HEADER.frame_id:
                self._header(bytes(data))
            elif frame_id == cf.FRAME_END.frame_id:
                return self._end(*cf.decode_frame_end(data))
            elif frame_id == cf.TIME_BASE.frame_id:
                self.t_base_us = cf.decode_time_base(data)
            elif frame_id == cf.END_OF_STREAM.frame_id:
                frames_sent, last_frame = cf.decode_end_of_stream(data)
                self._abandon()
                if self._last_frame is not None:
                    self.lost += (last_frame - self._last_frame) % (1 << 32)  # frames lost after the last received
                    self._last_frame = last_frame
                return EndOfStream(frames_sent=frames_sent)
        except cf.CanDecodeError:
            self.corrupt += 1
        return None

    def finish(self) -> None:
        """The input ended (the end of a capture): a frame still waiting for its end is dropped."""
        with self._lock:
            self._abandon()

    def _abandon(self) -> None:
        if self._frame is not None:
            self.incomplete += 1  # its FRAME_END never came (counted as lost at the next delivered frame)
            self._refused_pending += 1
            self._frame, self._stars = None, bytearray()

    def _header(self, header: bytes) -> None:
        self._abandon()
        frame, n_stars, t_offset_us = cf.decode_header(header)
        if self.t_base_us is None:
            self.corrupt += 1  # joined mid-stream before a time base: the exposure time is unknown
            return
        self._frame = (frame, n_stars, self.t_base_us + t_offset_us, header)

    def _star(self, data: bytes) -> None:
        if len(data) != cf.CAN_PAYLOAD_BYTES or self._frame is None:
            self.corrupt += 1
            return
        self._stars += data

    def _end(self, frame: int, frame_crc32: int) -> CentroidFrame | None:
        pending, stars = self._frame, bytes(self._stars)
        self._frame, self._stars = None, bytearray()
        if pending is None:
            self.corrupt += 1  # an end without its header
            return None
        number, n_stars, t_us, header = pending
        if len(stars) != n_stars * cf.CAN_PAYLOAD_BYTES:
            self.incomplete += 1
            self._refused_pending += 1
            return None
        if number != frame or cf.frame_check(t_us, header, stars) != frame_crc32:
            self.corrupt += 1
            self._refused_pending += 1
            return None
        if self._precedes_start(number):
            return None  # the end of a stream stopped before this one began: neither lost nor corrupt
        if self._awaiting_start:  # (only between a start and its ACK: a capture's assembler records nothing)
            self._delivered.append(number)
        if self._last_frame is not None:
            self.lost += (number - self._last_frame - 1) % (1 << 32)
            self.refused_between += self._refused_pending
        self._refused_pending = 0
        self._last_frame = number
        star_id, x, y, _ = cf.decode_stars(cf.payload_words(stars))
        return CentroidFrame(
            frame=number, t_us=t_us, star_id=star_id, x_px=x, y_px=y, mag=np.full(star_id.shape[0], math.nan)
        )


#: What python-can's serial-line adapters (slcan) raise for a garbled line (bad hex, bad digit, non-UTF-8, short
#: line): the line is skipped, the link goes on. A closed port raises CanOperationError and ends the link.
_ADAPTER_LINE_ERRORS = (ValueError, IndexError, KeyError)


def _garbled_line(exc: BaseException) -> bool:
    """True for a garbled adapter line (python-can wraps the slcan reader's UnicodeDecodeError in a
    CanOperationError); False for a port that is gone (its cause is an OSError / SerialException)."""
    return isinstance(exc, _ADAPTER_LINE_ERRORS) or isinstance(exc.__cause__, _ADAPTER_LINE_ERRORS)


#: Identifiers of the stream frames (everything StreamAssembler decodes).
STREAM_FRAME_IDS = frozenset(
    m.frame_id for m in (cf.STAR, cf.FRAME_HEADER, cf.FRAME_END, cf.TIME_BASE, cf.END_OF_STREAM)
)


# ---------------------------------------------------------------------------------------------- the link
@dataclass(frozen=True)
class _Counted:
    """A stream message in the inbox with the frames lost up to it (the assembler's count when it completed)."""

    message: Message
    lost: int


class CanLink(MessageLink):
    """Host node on a CAN bus (any python-can bus)."""

    #: A whole parameter table in one STAGE_CHUNK (one ISO-TP message of 59 bytes: 9 CAN frames).
    max_chunk_bytes = TABLE_BYTES

    def __init__(self, bus: can.BusABC, name: str, timeout_s: float = DEFAULT_TIMEOUT_S, owns_bus: bool = True) -> None:
        super().__init__(timeout_s)
        self.name = name
        self._bus = bus
        self._owns_bus = owns_bus  # False: a bus the caller opened (link_on_bus), left open on close
        self._tx_lock = threading.Lock()
        self._inbox: queue.SimpleQueue[Message | _Counted | None] = queue.SimpleQueue()
        self._assembler = StreamAssembler()
        self._isotp = IsoTpChannel(self._send_frame, cf.ISOTP_HOST_TO_SENSOR_ID, cf.ISOTP_SENSOR_TO_HOST_ID)
        self._failure: str | None = None
        self._start_tag: int | None = None  # tag of the STREAM_CONTROL(enable) whose ACK starts loss counting
        self._adapter_errors = 0  # garbled adapter lines skipped (see _resynchronise)
        self._closing = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name="can-link-reader", daemon=True)
        self._reader.start()

    # --------------------------------------------------------------------------------- bus side (thread)
    def _send_frame(self, msg: can.Message) -> None:
        with self._tx_lock:
            self._bus.send(msg, timeout=self.timeout_s)
        self.stats.tx_bytes += len(msg.data)

    def _read_loop(self) -> None:
        try:
            while not self._closing.is_set():
                try:
                    msg = self._bus.recv(_POLL_BUSY_S if self._isotp.busy else _POLL_IDLE_S)
                except (*_ADAPTER_LINE_ERRORS, can.CanOperationError) as exc:
                    if not _garbled_line(exc):
                        raise
                    self._resynchronise()
                    continue
                if msg is not None:
                    self._dispatch(msg)
                for payload in self._isotp.poll():
                    self._deliver_payload(payload)
        except Exception as exc:  # noqa: BLE001 - any bus failure ends the link with one line
            if not self._closing.is_set():
                self._failure = one_line(exc)
                self._inbox.put(None)  # wake a waiting _receive

    def _resynchronise(self) -> None:
        """A garbled line from a serial CAN adapter (SLCAN: a bad hex digit, a non-ASCII byte, a lost carriage
        return): count it and go on at the next line. python-can's slcan parser keeps an undecodable (non-UTF-8) line
        in its buffer; ``flush`` drops it (and bytes not yet read, whose frames are then counted as lost)."""
        self.stats.corrupt_frames += 1
        self._adapter_errors += 1
        flush = getattr(self._bus, "flush", None)
        if flush is not None:
            flush()

    def _dispatch(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        fid = msg.arbitration_id
        data = bytes(msg.data)
        self.stats.rx_bytes += len(data)
        if fid in STREAM_FRAME_IDS:
            self._heard()  # an intact CAN frame from the sensor (whatever the assembler makes of it)
            out = self._assembler.feed(fid, data)
            self.stats.corrupt_frames = self._assembler.corrupt + self._isotp.errors + self._adapter_errors
            if out is not None:
                self.stats.rx_messages += 1
                # with the loss counted up to it, taken into the stats when it is delivered (not now: the reader
                # thread may assemble later frames, and count their gaps, before the caller has this one)
                self._inbox.put(_Counted(out, self._assembler.lost))
        elif fid == cf.ISOTP_SENSOR_TO_HOST_ID:
            self._isotp.feed(msg)
        elif fid == cf.ACK.frame_id:
            try:
                ack = cf.decode_single(fid, data)
            except (cf.CanDecodeError, DecodeError):
                self.stats.corrupt_frames += 1
                return
            if self._start_tag is not None and isinstance(ack, Ack) and ack.tag == self._start_tag:
                # here, in bus order: the frames assembled before it are those sent before the stream's start
                # was known to this host, and begin_at sorts them
                self._assembler.begin_at(ack.value)
            self._inbox.put(ack)
            self.stats.rx_messages += 1

    def _deliver_payload(self, payload: bytes) -> None:
        try:
            self._inbox.put(decode(payload))
            self.stats.rx_messages += 1
        except DecodeError:
            self.stats.corrupt_frames += 1

    # ---------------------------------------------------------------------------------- transport hooks
    def _check_alive(self) -> None:
        if self._failure is not None:
            raise LinkError(f"{self.name}: CAN link lost ({self._failure})")
        if self._closing.is_set():
            raise LinkError(f"{self.name}: link is closed")

    def _send(self, msg: Message) -> None:
        self._check_alive()
        if isinstance(msg, StreamControl):
            self._start_tag = msg.tag if msg.enable else None
        try:
            if cf.is_single_frame(msg):
                fid, data = cf.encode_single(msg)
                self._send_frame(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
            else:
                self._isotp.send(encode(msg))
        except EncodeError as exc:
            raise LinkError(f"{self.name}: cannot encode {type(msg).__name__}: {exc}") from None
        except (can.CanError, OSError) as exc:
            raise LinkError(f"{self.name}: CAN send failed ({one_line(exc)})") from None

    def _receive(self, timeout_s: float) -> Message | None:
        self._check_alive()
        try:
            msg = self._inbox.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None
        if msg is None:
            self._check_alive()
        if isinstance(msg, _Counted):
            self.stats.lost_messages = msg.lost
            return msg.message
        return msg

    def _discard_input(self) -> None:
        while True:
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                return

    def _reset_loss_counting(self) -> None:
        self._assembler.forget_sequence()

    def _stream_started(self, first_frame: int) -> None:
        # the reader thread called begin_at when the ACK arrived; the frames it delivered before are in the
        # stream queue: those older than the stream are dropped, and the count is the assembler's up to the ACK
        self._stream = deque(
            m for m in self._stream if not (isinstance(m, CentroidFrame) and self._assembler.is_stale(m))
        )
        self.stats.lost_messages = self._assembler.lost_at_start

    def close(self) -> None:
        if self._closing.is_set():
            return
        self._closing.set()
        self._reader.join(1.0)
        if not self._owns_bus:
            return
        try:
            self._bus.shutdown()
        except (can.CanError, OSError):
            pass


def can_frames_for(frames: list[CentroidFrame]) -> int:
    """CAN frames the sensor puts on the bus for these centroid frames (``protocol.can_frames.StreamEncoder``: per
    frame a FRAME_HEADER, one STAR per star and a FRAME_END, plus the TIME_BASEs of its policy)."""
    encoder = cf.StreamEncoder()
    return sum(len(encoder.encode(f)) for f in frames)


def physical_limit_stars_per_s(frames: list[CentroidFrame], info: dict) -> float:
    """Most stars per second a CAN bus at ``info["bitrate"]`` carries for these frames: every frame is a worst-case
    8-byte standard frame of 135 bits (``protocol.can_frames.frame_bits_worst_case``), so stars/s = bitrate / 135 /
    (CAN frames per star). Benchmark hook of benchmarks/bench_links.py (hostlink/links/INTERFACE.md)."""
    stars = sum(f.n_stars for f in frames)
    bits = cf.frame_bits_worst_case(cf.CAN_PAYLOAD_BYTES, False)
    return float(info["bitrate"]) / bits * stars / can_frames_for(frames)
