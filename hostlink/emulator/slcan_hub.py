"""An emulated classic-CAN bus on 127.0.0.1 that speaks SLCAN (the Lawicel ASCII protocol) over TCP.

The emulated sensor has no CAN hardware to sit on, so this hub *is* the bus: every TCP client is an SLCAN adapter
(python-can's ``slcan`` interface opens it with ``channel="socket://127.0.0.1:PORT"``), and in-process nodes (the
emulated sensor) attach through :class:`HubBus`, a python-can bus. A frame sent by one node reaches every other open
node, and the bus is paced to its bit rate:

* every frame occupies the bus for its worst-case length (``protocol.can_frames.frame_bits_worst_case``; 135 bits
  for a standard 11-bit-ID frame with 8 data bytes, 160 bits for a 29-bit-ID one), so stars/s on the hub equal the
  physical limit of a real bus at the same bit rate, never more;
* when several nodes have a frame pending, the lowest identifier wins arbitration (ISO 11898-1); each node transmits
  its own frames in FIFO order (one TX mailbox chain, as firmware that streams must);
* the bus clock is virtual: a frame starts when the bus became free *and* the frame was pending, not when this thread
  got the CPU, so scheduling jitter on a loaded host delays delivery but does not cost bus time;
* a node's transmit queue is bounded (``tx_queue_frames``): a full queue blocks the sender (in-process nodes) or stops
  reading its socket (TCP clients), as a CAN controller's mailboxes do; a receiver that does not keep up loses frames
  (an RX overrun, counted in :attr:`SlcanHub.overruns`), as a real controller does.

SLCAN commands answered: ``O`` open, ``L`` listen-only, ``C`` close, ``S0``-``S8`` bit rate (must equal the hub's:
a node at another bit rate never joins the bus), ``s`` (BTR; refused), ``V`` version, ``N`` serial number, ``F``
status, ``Z``/``M``/``m``/``X``/``W``/``Q`` (accepted, no effect), and the frames ``tIIIL..``, ``TIIIIIIIIL..``,
``rIIIL``, ``RIIIIIIIIL``. A transmitted frame is answered ``z`` / ``Z`` (Lawicel), an error with BELL (0x07).
CAN FD frames (``d``, ``D``, ``b``, ``B``) are refused: this is a classic-CAN bus.
"""

from __future__ import annotations

import collections
import selectors
import socket
import threading
import time
from dataclasses import dataclass

import can

from protocol.can_frames import frame_bits_worst_case

#: SLCAN bit-rate codes (Lawicel ``Sn``), bit/s.
SLCAN_BITRATES: dict[str, int] = {
    "S0": 10_000,
    "S1": 20_000,
    "S2": 50_000,
    "S3": 100_000,
    "S4": 125_000,
    "S5": 250_000,
    "S6": 500_000,
    "S7": 750_000,
    "S8": 1_000_000,
    "S9": 83_300,
}
_OK = b"\r"
_ERR = b"\x07"
#: Bytes a TCP client may leave unread before the hub drops frames for it (RX overrun): ~10 000 frames.
_MAX_CLIENT_BACKLOG_BYTES = 256 * 1024
#: Frames an in-process node may leave unread before it overruns.
_MAX_LOCAL_RX_FRAMES = 65536


@dataclass(frozen=True, slots=True)
class HubFrame:
    """One classic CAN frame as it crosses the hub."""

    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    dlc: int
    data: bytes


def parse_slcan_frame(line: bytes) -> HubFrame | None:
    """Parse an SLCAN frame command (without the trailing CR); ``None`` if the line is not a valid classic frame."""
    if not line:
        return None
    kind = line[:1]
    id_len = {b"t": 3, b"r": 3, b"T": 8, b"R": 8}.get(kind)
    if id_len is None or len(line) < 2 + id_len:
        return None
    try:
        arbitration_id = int(line[1 : 1 + id_len], 16)
        dlc = int(line[1 + id_len : 2 + id_len], 16)
    except ValueError:
        return None
    extended = id_len == 8
    if dlc > 8 or arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    remote = kind in (b"r", b"R")
    payload = line[2 + id_len :]
    if remote:
        return HubFrame(arbitration_id, extended, True, dlc, b"")
    if len(payload) != 2 * dlc:
        return None
    try:
        data = bytes.fromhex(payload.decode("ascii"))
    except ValueError:
        return None
    return HubFrame(arbitration_id, extended, False, dlc, data)


def format_slcan_frame(frame: HubFrame) -> bytes:
    """The SLCAN line (with its CR) that reports ``frame`` to an adapter's host."""
    if frame.is_remote_frame:
        head = (
            f"R{frame.arbitration_id:08X}{frame.dlc:d}"
            if frame.is_extended_id
            else (f"r{frame.arbitration_id:03X}{frame.dlc:d}")
        )
        return head.encode("ascii") + _OK
    head = (
        f"T{frame.arbitration_id:08X}{frame.dlc:d}"
        if frame.is_extended_id
        else (f"t{frame.arbitration_id:03X}{frame.dlc:d}")
    )
    return head.encode("ascii") + frame.data.hex().upper().encode("ascii") + _OK


def _arbitration_key(frame: HubFrame) -> tuple[int, int, int, int]:
    """Sort key that reproduces bitwise arbitration: the 11 base-ID bits, then a standard frame beats an extended
    one (IDE recessive), then the 18 extension bits, then a data frame beats a remote frame (RTR recessive)."""
    if frame.is_extended_id:
        return (frame.arbitration_id >> 18, 1, frame.arbitration_id & 0x3FFFF, int(frame.is_remote_frame))
    return (frame.arbitration_id, 0, 0, int(frame.is_remote_frame))


class _Node:
    """One attachment to the bus (TCP SLCAN client or in-process python-can bus)."""

    def __init__(self, name: str, tx_queue_frames: int) -> None:
        self.name = name
        self.tx_queue_frames = tx_queue_frames
        self.is_open = False
        self.listen_only = False
        self.bitrate_ok = True
        self.tx: collections.deque[tuple[float, HubFrame]] = collections.deque()
        self.overruns = 0

    def deliver(self, frame: HubFrame, t_s: float) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


class _TcpNode(_Node):
    def __init__(self, sock: socket.socket, name: str, tx_queue_frames: int) -> None:
        super().__init__(name, tx_queue_frames)
        self.sock = sock
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.reading = True
        self.events = selectors.EVENT_READ

    def deliver(self, frame: HubFrame, t_s: float) -> None:
        if len(self.outbuf) > _MAX_CLIENT_BACKLOG_BYTES:
            self.overruns += 1
            return
        self.outbuf += format_slcan_frame(frame)


class _LocalNode(_Node):
    def __init__(self, name: str, tx_queue_frames: int) -> None:
        super().__init__(name, tx_queue_frames)
        self.is_open = True
        self.rx: collections.deque[tuple[float, HubFrame]] = collections.deque()
        self.rx_ready = threading.Condition()

    def deliver(self, frame: HubFrame, t_s: float) -> None:
        with self.rx_ready:
            if len(self.rx) >= _MAX_LOCAL_RX_FRAMES:
                self.overruns += 1
                return
            self.rx.append((t_s, frame))
            self.rx_ready.notify()


class SlcanHub:
    """The emulated bus: a TCP SLCAN server on ``host:port`` plus in-process nodes, paced to ``bitrate`` bit/s.

    ``start()`` runs it on a daemon thread; ``stop()`` ends it and closes every client. ``port=0`` picks a free port
    (read :attr:`port` / :attr:`url` after ``start``).
    """

    def __init__(
        self, bitrate: int = 500_000, host: str = "127.0.0.1", port: int = 0, tx_queue_frames: int = 16
    ) -> None:
        if int(bitrate) not in SLCAN_BITRATES.values():
            allowed = ", ".join(str(v) for v in sorted(SLCAN_BITRATES.values()))
            raise ValueError(f"CAN bit rate {bitrate} is not an SLCAN rate (allowed: {allowed})")
        if tx_queue_frames < 1:
            raise ValueError("tx_queue_frames must be >= 1")
        self.bitrate = int(bitrate)
        self.bitrate_code = next(k for k, v in SLCAN_BITRATES.items() if v == self.bitrate)
        self.tx_queue_frames = int(tx_queue_frames)
        self._listener = socket.create_server((host, port))
        self._listener.setblocking(False)
        self.host, self.port = self._listener.getsockname()[:2]
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, None)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._lock = threading.Lock()  # guards node lists and every node's tx deque
        self._tx_space = threading.Condition(self._lock)
        self._nodes: list[_Node] = []
        self._bus_free_at = 0.0
        self._in_flight: tuple[float, HubFrame, _Node] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_on_bus = 0
        self.bits_on_bus = 0

    # ------------------------------------------------------------------ public
    @property
    def url(self) -> str:
        """The pyserial URL a python-can ``slcan`` bus opens: ``socket://127.0.0.1:PORT``."""
        return f"socket://{self.host}:{self.port}"

    @property
    def overruns(self) -> int:
        """Frames dropped because a receiving node did not keep up (summed over nodes)."""
        with self._lock:
            return sum(n.overruns for n in self._nodes)

    def start(self) -> SlcanHub:
        self._thread = threading.Thread(target=self._run, name="slcan-hub", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(2.0)
        for key in list(self._sel.get_map().values()):
            try:
                key.fileobj.close()
            except OSError:
                pass
        self._sel.close()
        self._wake_w.close()
        for node in list(self._nodes):
            if isinstance(node, _LocalNode):
                with node.rx_ready:
                    node.rx_ready.notify_all()

    def attach(self, name: str = "local", tx_queue_frames: int | None = None) -> HubBus:
        """A python-can bus for an in-process node (the emulated sensor); ``tx_queue_frames`` overrides the hub's
        transmit queue depth for this node (a firmware's software TX ring in front of its mailboxes)."""
        node = _LocalNode(name, int(tx_queue_frames or self.tx_queue_frames))
        with self._lock:
            self._nodes.append(node)
        return HubBus(self, node)

    # -------------------------------------------------------- node interface
    def _submit(self, node: _Node, frame: HubFrame, timeout: float | None) -> bool:
        """Queue a frame for transmission; blocks while the node's queue is full. False on timeout or stop."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._tx_space:
            while len(node.tx) >= node.tx_queue_frames and not self._stop.is_set():
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._tx_space.wait(left)
            if self._stop.is_set():
                return False
            node.tx.append((time.monotonic(), frame))
        self._wake()
        return True

    def _detach(self, node: _Node) -> None:
        with self._lock:
            if node in self._nodes:
                self._nodes.remove(node)
            node.tx.clear()
            self._tx_space.notify_all()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already awake (buffer full) or stopped

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                timeout = self._advance_bus()
                for key, mask in self._sel.select(timeout):
                    if key.data is None:
                        self._accept()
                    elif key.data == "wake":
                        try:
                            while self._wake_r.recv(4096):
                                pass
                        except BlockingIOError:
                            pass
                    else:
                        node = key.data
                        if mask & selectors.EVENT_READ:
                            self._read_client(node)
                        if mask & selectors.EVENT_WRITE and node.sock.fileno() >= 0:
                            self._flush_client(node)
        except OSError:
            if not self._stop.is_set():
                raise

    def _advance_bus(self) -> float | None:
        """Complete every frame whose bus time has passed, start the next one; seconds until the next event."""
        while True:
            now = time.monotonic()
            if self._in_flight is not None:
                done_at, frame, sender = self._in_flight
                if done_at > now:
                    return done_at - now
                self._in_flight = None
                self._deliver(frame, sender, done_at)
            with self._lock:
                heads = [(n.tx[0][0], n) for n in self._nodes if n.tx]
                if not heads:
                    return None
                # Arbitration happens when the bus goes idle: among frames already pending then, lowest ID wins;
                # if none was pending, the bus stayed idle until the earliest one arrived.
                ready = [(t, n) for t, n in heads if t <= self._bus_free_at]
                if ready:
                    _, node = min(ready, key=lambda tn: _arbitration_key(tn[1].tx[0][1]))
                else:
                    _, node = min(heads, key=lambda tn: tn[0])
                pending_since, frame = node.tx.popleft()
                self._tx_space.notify_all()
                resume = isinstance(node, _TcpNode) and not node.reading
            if resume:  # the sender's mailboxes have room again: take its queued commands
                node.reading = True
                self._process_lines(node)
            start = max(self._bus_free_at, pending_since)
            bits = frame_bits_worst_case(frame.dlc, frame.is_extended_id, frame.is_remote_frame)
            self._bus_free_at = start + bits / self.bitrate
            self.frames_on_bus += 1
            self.bits_on_bus += bits
            self._in_flight = (self._bus_free_at, frame, node)

    def _deliver(self, frame: HubFrame, sender: _Node, t_s: float) -> None:
        with self._lock:
            receivers = [n for n in self._nodes if n is not sender and n.is_open and n.bitrate_ok]
        for node in receivers:
            node.deliver(frame, t_s)
            if isinstance(node, _TcpNode):
                self._flush_client(node)

    def _accept(self) -> None:
        try:
            sock, peer = self._listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        node = _TcpNode(sock, f"{peer[0]}:{peer[1]}", self.tx_queue_frames)
        with self._lock:
            self._nodes.append(node)
        self._sel.register(sock, selectors.EVENT_READ, node)

    def _update_interest(self, node: _TcpNode) -> None:
        events = (selectors.EVENT_READ if node.reading else 0) | (selectors.EVENT_WRITE if node.outbuf else 0)
        events = events or selectors.EVENT_READ  # stay registered to see a close
        if events == node.events:
            return
        try:
            self._sel.modify(node.sock, events, node)
            node.events = events
        except (KeyError, ValueError, OSError):
            pass

    def _drop_client(self, node: _TcpNode) -> None:
        try:
            self._sel.unregister(node.sock)
        except (KeyError, ValueError):
            pass
        node.sock.close()
        self._detach(node)

    def _read_client(self, node: _TcpNode) -> None:
        try:
            chunk = node.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
        if not chunk:
            self._drop_client(node)
            return
        node.inbuf += chunk
        self._process_lines(node)

    def _process_lines(self, node: _TcpNode) -> None:
        replies = bytearray()
        while True:
            cut = node.inbuf.find(b"\r")
            if cut < 0:
                break
            line = bytes(node.inbuf[:cut]).lstrip(b"\n")
            del node.inbuf[: cut + 1]
            replies += self._command(node, line)
            with self._lock:
                full = len(node.tx) >= node.tx_queue_frames
            if full:  # a controller with full mailboxes: stop taking commands until the bus drains
                node.reading = False
                break
        if len(node.inbuf) > 4096:  # no CR in 4 KiB: not SLCAN
            node.inbuf.clear()
            replies += _ERR
        node.outbuf += replies
        self._flush_client(node)

    def _command(self, node: _TcpNode, line: bytes) -> bytes:
        """Execute one SLCAN command; the reply bytes."""
        if not line:
            return _OK
        op = line[:1]
        if op in (b"t", b"T", b"r", b"R"):
            frame = parse_slcan_frame(line)
            if frame is None or not node.is_open or node.listen_only or not node.bitrate_ok:
                return _ERR
            with self._lock:
                node.tx.append((time.monotonic(), frame))
            return (b"Z" if frame.is_extended_id else b"z") + _OK
        if op in (b"O", b"L"):
            if not node.bitrate_ok:
                return _ERR
            node.is_open, node.listen_only = True, op == b"L"
            return _OK
        if op == b"C":
            node.is_open = False
            return _OK
        if op == b"S":
            node.bitrate_ok = line.decode("ascii", "replace") == self.bitrate_code
            return _OK if node.bitrate_ok else _ERR
        if op == b"V":
            return b"V1013" + _OK
        if op == b"N":
            return b"NHUB0" + _OK
        if op == b"F":
            return b"F00" + _OK
        if op in (b"Z", b"M", b"m", b"X", b"W", b"Q"):
            return _OK
        return _ERR  # 's' (BTR), CAN FD frames and anything unknown

    def _flush_client(self, node: _TcpNode) -> None:
        if node.outbuf:
            try:
                sent = node.sock.send(node.outbuf)
                del node.outbuf[:sent]
            except BlockingIOError:
                pass
            except OSError:
                self._drop_client(node)
                return
        self._update_interest(node)


class HubBus(can.BusABC):
    """python-can bus of an in-process node on a :class:`SlcanHub` (used by the emulated sensor)."""

    def __init__(self, hub: SlcanHub, node: _LocalNode, **kwargs: object) -> None:
        self._hub = hub
        self._node = node
        self.channel_info = f"slcan-hub node {node.name} on {hub.url}"
        super().__init__(channel=hub.url, **kwargs)

    @property
    def overruns(self) -> int:
        return self._node.overruns

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd:
            raise can.CanOperationError("the emulated bus is classic CAN: no FD frames")
        frame = HubFrame(
            int(msg.arbitration_id), bool(msg.is_extended_id), bool(msg.is_remote_frame), int(msg.dlc), bytes(msg.data)
        )
        if not self._hub._submit(self._node, frame, timeout):
            raise can.CanOperationError("transmit queue full (bus busy) or bus stopped")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        node = self._node
        with node.rx_ready:
            if not node.rx:
                node.rx_ready.wait(timeout)
            if not node.rx:
                return None, False
            t_s, frame = node.rx.popleft()
        msg = can.Message(
            timestamp=t_s,
            arbitration_id=frame.arbitration_id,
            is_extended_id=frame.is_extended_id,
            is_remote_frame=frame.is_remote_frame,
            dlc=frame.dlc,
            data=frame.data,
        )
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self._hub._detach(self._node)
