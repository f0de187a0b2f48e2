"""A fault-injecting relay between a host and a sensor (a host-side test tool): bit errors, byte drops and cuts on
any byte-stream link of this project: serial (a pty in front of the sensor's pty), CAN through an SLCAN adapter on
TCP, Modbus TCP and Modbus RTU over TCP.

Fault model (:class:`FaultModel`), applied independently to every byte that passes in a faulty direction: the byte is
dropped with probability ``drop``; a byte that passes has each of its 8 bits flipped with probability ``ber`` (a
binary symmetric channel). ``cut_after_bytes``: after that many bytes in that direction the relay closes the link for
good (the sensor is gone: the host must end with one line, exit 3). Seeded (numpy PCG64): a run is reproducible.

Command line (prints one JSON line ``{"link": RELAYED_LINK, ...}`` and relays until interrupted)::

    python -m hostlink.emulator.fault_relay --link LINK [--ber 1e-4] [--drop 0.01] [--seed 0]
                                            [--direction down|up|both] [--cut-after BYTES]

``LINK`` is the link string the emulator printed (``serial:/dev/pts/N@BAUD``, ``can:slcan:socket://H:P@BITRATE``,
``modbus-tcp:H:P``, ``modbus-rtu:tcp://H:P``); the printed link goes through the relay. ``down`` is sensor -> host.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import select
import socket
import sys
import threading
import tty
from dataclasses import dataclass, field

import numpy as np

_CHUNK = 4096
_POLL_S = 0.05


@dataclass
class FaultModel:
    """Faults of one direction: byte drop probability, bit error rate, cut after a byte count (None: never)."""

    ber: float = 0.0
    drop: float = 0.0
    seed: int = 0
    cut_after_bytes: int | None = None
    bytes_in: int = 0
    bytes_dropped: int = 0
    bits_flipped: int = 0
    bytes_corrupted: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not (0.0 <= self.ber <= 1.0 and 0.0 <= self.drop <= 1.0):
            raise ValueError("ber and drop are probabilities in [0, 1]")
        self._rng = np.random.default_rng(self.seed)

    @property
    def cut(self) -> bool:
        return self.cut_after_bytes is not None and self.bytes_in >= self.cut_after_bytes

    def apply(self, data: bytes) -> bytes:
        """The bytes that come out of the faulty line for ``data`` (fewer, some flipped)."""
        if self.cut_after_bytes is not None:
            data = data[: max(0, self.cut_after_bytes - self.bytes_in)]
        self.bytes_in += len(data)
        if not data or (self.ber == 0.0 and self.drop == 0.0):
            return data
        arr = np.frombuffer(data, dtype=np.uint8)
        # one row of draws per byte (drop, then its 8 bits): the faults hit the same bytes however the stream is cut
        # into reads, so a seed gives one fault pattern per byte stream
        draws = self._rng.random((arr.size, 9))
        keep = draws[:, 0] >= self.drop
        flips = (draws[:, 1:] < self.ber)[keep]
        arr = arr[keep]
        mask = np.packbits(flips, axis=1)[:, 0] if arr.size else np.zeros(0, np.uint8)
        self.bytes_dropped += int(np.count_nonzero(~keep))
        self.bits_flipped += int(np.count_nonzero(flips))
        self.bytes_corrupted += int(np.count_nonzero(mask))
        return (arr ^ mask).tobytes()

    def counts(self) -> dict:
        return {
            "bytes_in": self.bytes_in,
            "bytes_dropped": self.bytes_dropped,
            "bytes_corrupted": self.bytes_corrupted,
            "bits_flipped": self.bits_flipped,
        }


def _pump(src_read, dst_write, model: FaultModel, stop: threading.Event, on_end, on_cut) -> None:  # noqa: ANN001
    """Copy bytes from ``src_read`` to ``dst_write`` through ``model`` until EOF (then ``on_end``), a cut (then
    ``on_cut``: the whole relay is gone) or ``stop``."""
    while not stop.is_set():
        data = src_read()
        if data is None:
            continue
        if not data:
            break
        out = model.apply(data)
        if out:
            try:
                dst_write(out)
            except OSError:
                break
        if model.cut:
            on_cut()
            return
    on_end()


class TcpRelay:
    """Listens on 127.0.0.1 (an ephemeral port) and relays each accepted connection to ``target`` through ``down``
    (target -> client) and ``up`` (client -> target)."""

    def __init__(self, target: tuple[str, int], down: FaultModel, up: FaultModel | None = None) -> None:
        self.target = target
        self.down, self.up = down, up or FaultModel()
        self.stop = threading.Event()
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(_POLL_S)
        self.port = self._server.getsockname()[1]
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._accept_loop, daemon=True)]
        self._threads[0].start()

    def _accept_loop(self) -> None:
        while not self.stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(_POLL_S)
            with self._lock:
                self._sockets += [client, upstream]
                self._threads = [t for t in self._threads if t.is_alive()]  # the pumps of connections that ended
            pumps_left = [2]  # the pump that ends last closes the pair (its file descriptors; a host that
            # reconnects after every few failed exchanges opens thousands of connections in a long run)

            def end(pair: tuple[socket.socket, ...] = (client, upstream), left: list[int] = pumps_left) -> None:
                for s in pair:  # this connection is over (either side closed it); the relay goes on
                    try:
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                with self._lock:
                    left[0] -= 1
                    if left[0] > 0:
                        return
                    for s in pair:
                        s.close()
                        if s in self._sockets:
                            self._sockets.remove(s)

            for src, dst, model in ((upstream, client, self.down), (client, upstream, self.up)):
                t = threading.Thread(
                    target=_pump,
                    args=(_sock_reader(src), dst.sendall, model, self.stop, end, self.cut),
                    daemon=True,
                )
                t.start()
                self._threads.append(t)

    def cut(self) -> None:
        """The link is gone: every connection closed, no new ones accepted."""
        self.stop.set()
        with self._lock:
            for s in [self._server, *self._sockets]:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    close = cut


def _sock_reader(s: socket.socket):  # noqa: ANN202
    def read() -> bytes | None:
        try:
            return s.recv(_CHUNK)
        except TimeoutError:
            return None
        except OSError:
            return b""

    return read


class PtyRelay:
    """Opens the sensor's pty ``device`` and offers a new pty (:attr:`device`) to the host, relaying through the
    fault models."""

    def __init__(self, sensor_device: str, down: FaultModel, up: FaultModel | None = None) -> None:
        self.down, self.up = down, up or FaultModel()
        self.stop = threading.Event()
        self._sensor_fd = os.open(sensor_device, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self._sensor_fd)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.device = os.ttyname(self._slave)
        self._closed = False
        self._threads = [
            threading.Thread(
                target=_pump,
                args=(_fd_reader(a), _fd_writer(b), model, self.stop, self.cut, self.cut),
                daemon=True,
            )
            for a, b, model in ((self._sensor_fd, self._master, self.down), (self._master, self._sensor_fd, self.up))
        ]
        for t in self._threads:
            t.start()

    def cut(self) -> None:
        """The line is gone: the host's pty is hung up (reads fail), the sensor's side closed."""
        if self._closed:
            return
        self._closed = True
        self.stop.set()
        for fd in (self._master, self._sensor_fd):
            try:
                os.close(fd)
            except OSError:
                pass

    def close(self) -> None:
        self.cut()
        try:
            os.close(self._slave)
        except OSError:
            pass


def _fd_reader(fd: int):  # noqa: ANN202
    def read() -> bytes | None:
        try:
            ready, _, _ = select.select([fd], [], [], _POLL_S)
            return os.read(fd, _CHUNK) if ready else None
        except OSError:
            return b""

    return read


def _fd_writer(fd: int):  # noqa: ANN202
    def write(data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]

    return write


_TCP_IN_LINK = re.compile(r"^(?P<head>.*?)(?P<host>[0-9A-Za-z_.\-]+):(?P<port>\d+)(?P<tail>(@\d+)?(,.*)?)$")


def relay_link(link: str, down: FaultModel, up: FaultModel | None = None) -> tuple[str, TcpRelay | PtyRelay]:
    """Start a relay in front of ``link`` (a link string); returns the relayed link string and the relay."""
    if link.startswith("serial:"):
        device, at, baud = link[len("serial:") :].rpartition("@")
        device = device if at else link[len("serial:") :]
        relay = PtyRelay(device, down, up)
        return f"serial:{relay.device}" + (f"@{baud}" if at else ""), relay
    m = _TCP_IN_LINK.match(link)
    if m is None or not link.startswith(("can:", "modbus-tcp:", "modbus-rtu:")):
        raise ValueError(f"{link}: not a link the relay can stand in (serial pty, TCP: SLCAN, Modbus)")
    tcp = TcpRelay((m["host"], int(m["port"])), down, up)
    return f"{m['head']}127.0.0.1:{tcp.port}{m['tail']}", tcp


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hostlink.emulator.fault_relay", description=__doc__.split("\n")[0])
    parser.add_argument("--link", required=True, help="the sensor's link string (as the emulator printed it)")
    parser.add_argument("--ber", type=float, default=1e-4, help="bit error rate per bit (default 1e-4)")
    parser.add_argument("--drop", type=float, default=0.01, help="byte drop probability (default 0.01)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--direction", choices=("down", "up", "both"), default="down", help="down: sensor -> host")
    parser.add_argument("--cut-after", type=int, default=None, metavar="BYTES", help="cut the link after BYTES down")
    args = parser.parse_args(argv)
    try:
        faulty = FaultModel(args.ber, args.drop, args.seed, args.cut_after)
        clean = FaultModel(seed=args.seed + 1)
        down = faulty if args.direction in ("down", "both") else clean
        up = FaultModel(args.ber, args.drop, args.seed + 1) if args.direction in ("up", "both") else clean
        link, relay = relay_link(args.link, down, up)
    except (ValueError, OSError) as exc:
        print(f"fault_relay: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"link": link, "ber": args.ber, "drop": args.drop, "direction": args.direction}), flush=True)
    try:
        relay.stop.wait()
    except KeyboardInterrupt:
        pass
    relay.close()
    print(json.dumps({"down": down.counts(), "up": up.counts()}), file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
