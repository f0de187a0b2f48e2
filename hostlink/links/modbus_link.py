"""Modbus link: the sensor's commands as register reads and writes laid out by ``protocol/modbus_map.json``; all
pymodbus calls go through ``hostlink.links.modbus_adapter``.

Link strings:

* ``modbus-tcp:HOST:PORT[,unit=N]`` -- Modbus TCP (what ``hostlink emulate --transport modbus`` prints as ``link``);
* ``modbus-rtu:tcp://HOST:PORT[,unit=N]`` -- RTU framing over TCP (an RS-485 gateway; the emulator's ``link_rtu``);
* ``modbus-rtu:/dev/ttyUSB0[@BAUD][,unit=N,parity=E]`` -- RTU on a serial line (default 19200 baud, even parity).

``unit`` defaults to the map's ``unit_id`` (1); ``response_timeout_ms`` is how long the device may take to answer
(default 200 ms, plus the answer's line time on a serial line). A command is one write of the argument registers
and ``command`` (function code 16), then one read of the ``result_*`` registers; a NAK becomes
:class:`CommandRefused` with the sensor's code and text. The stream is polled: read the window, release it with
``stream_ack_seq``; lost messages are counted from gaps in ``window_seq``.

Integrity and recovery: every block read as a snapshot (result, status, tables, estimate, stream window) carries a
CRC-32 check register (``checked_blocks`` in the map); a block whose check fails is read again, never decoded. An
exchange that fails on the way (timeout, garbled or short answer) is counted in ``stats.corrupt_frames``, the
connection is reset (stale bytes dropped), reads shrink to fewer registers per request, and the exchange is made
again until the deadline; then one LinkError (the link is gone). Command writes are repeated only for commands that
may run twice (STREAM_CONTROL, STAGE_CHUNK, STAGE_VERIFY).
"""

from __future__ import annotations

import time

import numpy as np

from hostlink.errors import LinkError, UserError
from hostlink.links.base import DEFAULT_TIMEOUT_S, CommandRefused, Link
from hostlink.links.modbus_adapter import ModbusAdapterError, RegisterClient
from protocol import modbus_map as mm
from protocol.messages import (
    ESTIMATE_FIELDS,
    CentroidFrame,
    Estimate,
    MsgType,
    ParamTable,
    TableBank,
    Telemetry,
    dequantise_mag,
    dequantise_px,
)
from protocol.param_table import N_FIELDS, PARAM_FIELDS, TABLE_BYTES

DEFAULT_RTU_BAUD = 19200
#: Wait between two polls of an empty stream window [s].
_POLL_S = 0.002
_RESULT_ACK, _RESULT_NAK = 1, 2
_WINDOW_FRAME, _WINDOW_END = 1, 2
#: Exchanges a lost answer may cost within one link timeout, at least (each waits at most timeout / this).
_ATTEMPTS_PER_TIMEOUT = 4
#: A device's time to answer on top of the line time [s] (Modbus over serial line v1.02: a slave answers within
#: its response timeout, typically 100 ms or less; TCP on a LAN well under that).
_ANSWER_LATENCY_S = 0.2
#: Consecutive failed exchanges after which the connection is opened again (a partial answer left behind spoils the
#: next exchange at most; pymodbus drops what does not parse).
_RESET_AFTER_FAILURES = 2
#: Pause before an exchange is made again after a failure [s].
_RETRY_PAUSE_S = 0.005
#: Smallest read after failures on a noisy line [registers]: 16 registers = a 41-byte RTU answer.
_MIN_CHUNK = 16
#: Commands that may be written again after a failure on the way (running them twice is running them once).
_IDEMPOTENT = (MsgType.STREAM_CONTROL, MsgType.STAGE_CHUNK, MsgType.STAGE_VERIFY)


def parse_target(scheme: str, target: str) -> dict:
    """Keyword arguments of :class:`RegisterClient` for a link string; one-line UserError if malformed."""
    usage = (
        f"--link {scheme}:{target}: expected modbus-tcp:HOST:PORT[,unit=N], modbus-rtu:tcp://HOST:PORT[,unit=N] "
        "or modbus-rtu:/dev/ttyUSB0[@BAUD][,unit=N,parity=E] (any of them with ,response_timeout_ms=N)"
    )
    main, *opts = target.split(",")
    kw: dict = {"unit": mm.load_map().unit_id}
    for opt in opts:
        key, eq, value = opt.partition("=")
        key, value = key.strip(), value.strip()
        if not eq:
            raise UserError(usage)
        if key == "unit" and value.isdigit() and 0 <= int(value) <= 247:
            kw["unit"] = int(value)
        elif key == "response_timeout_ms" and value.isdigit() and int(value) > 0:
            kw["response_timeout_s"] = int(value) / 1000.0
        elif key == "parity" and value.upper() in ("N", "E", "O") and scheme == "modbus-rtu":
            kw["parity"] = value.upper()
        else:
            raise UserError(usage)
    if scheme == "modbus-rtu" and not main.startswith("tcp://"):
        port, at, baud = main.rpartition("@")
        if not at:
            port, baud = main, str(DEFAULT_RTU_BAUD)
        if not port or not baud.isdigit():
            raise UserError(usage)
        kw.update(serial_port=port, baud=int(baud), framing="rtu")
        return kw
    hostport = main[len("tcp://") :] if main.startswith("tcp://") else main
    host, colon, port_text = hostport.rpartition(":")
    if not colon or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise UserError(usage)
    kw.update(host=host, port=int(port_text), framing="rtu" if scheme == "modbus-rtu" else "tcp")
    return kw


def open_link(scheme: str, target: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> ModbusLink:
    kw = parse_target(scheme, target)
    try:
        response_s = kw.pop("response_timeout_s", None)
        client = RegisterClient(timeout_s=attempt_timeout_s(timeout_s, kw.get("baud"), response_s), **kw)
    except ModbusAdapterError as exc:
        raise LinkError(f"{scheme}:{target}: {exc}") from None
    return ModbusLink(client, f"{scheme}:{target}", timeout_s)


def attempt_timeout_s(timeout_s: float, baud: int | None, response_s: float | None = None) -> float:
    """How long one exchange waits for its answer [s]: the longest answer's line time (256 bytes of 11 bits at
    ``baud`` on a serial line, none on TCP) plus the device's response time (``response_timeout_ms`` in the link
    string, default _ANSWER_LATENCY_S), but at most a quarter of the link timeout, so that an answer lost on a noisy
    line is asked for again several times within the timeout."""
    line_s = 256 * 11 / baud if baud else 0.0
    return min(timeout_s / _ATTEMPTS_PER_TIMEOUT, line_s + (_ANSWER_LATENCY_S if response_s is None else response_s))


class ModbusLink(Link):
    """A sensor on Modbus (TCP, RTU over TCP, RTU serial)."""

    #: A whole table per STAGE_CHUNK (the staging mailbox holds every table value).
    max_chunk_bytes = TABLE_BYTES

    def __init__(
        self,
        client: RegisterClient,
        name: str,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        regmap: mm.ModbusMap | None = None,
    ) -> None:
        super().__init__()
        self.name = name
        self.timeout_s = float(timeout_s)
        self._client = client
        self.map = regmap or mm.load_map()
        self._last_seq: int | None = None
        self._ended = False
        self._closed = False
        m = self.map
        self._cmd_block = m.block("holding", "command_arg", "command")
        self._result_block = m.block("input", "result_command", "result_text")
        self._status_block = m.block("input", "status_streaming", "status_estimator_updates")
        self._stage_first = m[f"stage_{PARAM_FIELDS[0]}"].address
        star_regs = [m[n] for n in ("window_star_x_px", "window_star_y_px", "window_star_id", "window_star_mag")]
        self._star_regs = star_regs
        self._window_first = m["window_state"].address
        self._star_first = min(r.address for r in star_regs)
        self._star_stride = star_regs[0].stride
        #: stars that fit in the first read of the window (header + whole stars <= 125 registers)
        self._stars_in_head = (mm.MAX_READ_REGISTERS - (self._star_first - self._window_first)) // self._star_stride
        self._window_block = m.checked_block("window")
        self._chunk = mm.MAX_READ_REGISTERS  # registers per read: halved after a failed read, doubled after a good one

    # ------------------------------------------------------------------------------------ register I/O
    def _read(self, table: str, address: int, count: int, deadline: float | None = None) -> list[int]:
        """``count`` registers from ``address``, in reads of at most the current chunk size; a read that fails on the
        way (timeout, garbled or short answer) is counted in ``stats.corrupt_frames`` and made again, with smaller
        chunks, until ``deadline`` (default: the link timeout from now); then LinkError (the link is gone)."""
        self._check_open()
        deadline = time.monotonic() + self.timeout_s if deadline is None else deadline
        out: list[int] = []
        while count > 0:
            n = min(count, self._chunk)
            out += self._attempt(lambda n=n, a=address: self._client.read(table, a, n), deadline)
            address, count = address + n, count - n
        self.stats.rx_bytes += 2 * len(out)
        return out

    def _write(self, address: int, values: list[int], retry: bool = True, deadline: float | None = None) -> None:
        """Write holding registers; ``retry``: the write may be made again after a failure on the way (it must be
        idempotent: a command that could run twice is written once, and a failure is a LinkError)."""
        self._check_open()
        deadline = time.monotonic() + self.timeout_s if deadline is None else deadline
        self._attempt(lambda: self._client.write(address, values), deadline if retry else time.monotonic())
        self.stats.tx_bytes += 2 * len(values)

    def _attempt(self, exchange, deadline: float):  # noqa: ANN001, ANN202 - a client call and its result
        """One Modbus exchange, made again after failures on the way until ``deadline``. A Modbus exception answer
        (the device refused) is final."""
        failures = 0
        while True:
            try:
                result = exchange()
            except ModbusAdapterError as exc:
                # an exception answer is final on a clean line, but on a noisy one it may itself be a corrupted
                # answer (Modbus TCP has no checksum): asked again like any failed exchange, until the deadline
                if time.monotonic() >= deadline:
                    raise LinkError(f"{self.name}: {exc}") from None
                self.stats.corrupt_frames += 1
                failures += 1
                self._chunk = max(_MIN_CHUNK, self._chunk // 2)  # smaller answers survive a noisy line more often
                if failures % _RESET_AFTER_FAILURES == 0:
                    self._client.reset()  # resynchronise: stale or partial bytes of failed exchanges are dropped
                time.sleep(_RETRY_PAUSE_S)  # a refused connection fails at once: do not spin
                continue
            self._chunk = min(mm.MAX_READ_REGISTERS, self._chunk * 2)
            return result

    def _read_block(self, name: str, deadline: float | None = None) -> list[int]:
        """The registers of a checked block (``protocol/modbus_map.json`` ``checked_blocks``), read again until its
        check matches (each mismatch counted in ``stats.corrupt_frames``) or ``deadline`` (LinkError)."""
        block = self.map.checked_block(name)
        deadline = time.monotonic() + self.timeout_s if deadline is None else deadline
        while True:
            lo, count = block.read_span()
            words = self._read("input", lo, count, deadline)
            if mm.block_intact(block, words, lo):
                return words
            self.stats.corrupt_frames += 1
            if time.monotonic() >= deadline:
                raise LinkError(f"{self.name}: the {name} registers fail their check (block_check) on every read")

    def _check_open(self) -> None:
        if self._closed:
            raise LinkError(f"{self.name}: link is closed")

    def _get(self, words: list[int], base: int, name: str) -> int | float | str:
        return mm.get(words, self.map[name], base=base)

    # ---------------------------------------------------------------------------------------- commands
    def _command(self, msg_type: MsgType, arg: int = 0, length: int = 0, crc32: int = 0) -> int:
        """Run one command through the command registers; its ACK value, or CommandRefused."""
        m = self.map
        lo, count = self._cmd_block
        words = [0] * count
        for name, value in (
            ("command_arg", arg),
            ("command_length", length),
            ("command_crc32", crc32),
            ("command", int(msg_type)),
        ):
            reg = m[name]
            words[reg.address - lo : reg.address - lo + reg.width] = mm.to_registers(reg, value)
        self._write(lo, words, retry=msg_type in _IDEMPOTENT)
        rlo, _ = self._result_block
        res = self._read_block("result")
        if self._get(res, rlo, "result_command") != int(msg_type):
            raise LinkError(
                f"{self.name}: the sensor reports command {self._get(res, rlo, 'result_command')} "
                f"as its last, not {msg_type.name}"
            )
        status = self._get(res, rlo, "result_status")
        if status == _RESULT_NAK:
            raise CommandRefused(
                int(msg_type), int(self._get(res, rlo, "result_code")), str(self._get(res, rlo, "result_text"))
            )
        if status != _RESULT_ACK:
            raise LinkError(f"{self.name}: no result for {msg_type.name} (result_status {status})")
        self.stats.rx_messages += 1
        return int(self._get(res, rlo, "result_value"))

    def status(self) -> Telemetry:
        lo, _ = self._status_block
        w = self._read_block("status")
        self.stats.rx_messages += 1
        return Telemetry(
            streaming=bool(self._get(w, lo, "status_streaming")),
            stage_state=int(self._get(w, lo, "status_stage_state")),
            active_generation=int(self._get(w, lo, "status_active_generation")),
            active_crc32=int(self._get(w, lo, "status_active_crc32")),
            frames_processed=int(self._get(w, lo, "status_frames_processed")),
            last_frame=int(self._get(w, lo, "status_last_frame")),
            estimator_updates=int(self._get(w, lo, "status_estimator_updates")),
        )

    def set_streaming(self, enable: bool) -> None:
        self._command(MsgType.STREAM_CONTROL, arg=1 if enable else 0)
        self._ended = False
        if enable:
            self._last_seq = None
            self.stats.lost_messages = 0
            self.stats.corrupt_frames = 0

    def stage_begin(self, length: int) -> int:
        return self._command(MsgType.STAGE_BEGIN, arg=length)

    def stage_chunk(self, offset: int, data: bytes) -> None:
        data = bytes(data)
        if offset < 0 or offset + len(data) > TABLE_BYTES:
            # the mailbox holds one table: a chunk outside it cannot be carried (the firmware would refuse it too)
            raise LinkError(f"{self.name}: chunk {offset}..{offset + len(data)} outside the {TABLE_BYTES}-byte table")
        first, last = offset // 4, (offset + len(data) + 3) // 4
        addr = self._stage_first + 2 * first
        if offset % 4 or len(data) % 4:  # partial values: merge with what the mailbox holds
            old = mm.table_from_registers(self._read("holding", addr, 2 * (last - first)))
            start = offset - 4 * first
            patch = old[:start] + data + old[start + len(data) :]
        else:
            patch = data
        self._write(addr, mm.registers_from_table(patch))
        self._command(MsgType.STAGE_CHUNK, arg=offset, length=len(data))

    def stage_verify(self, crc32: int) -> None:
        self._command(MsgType.STAGE_VERIFY, crc32=crc32)

    def commit(self, crc32: int, nonce: int = 0, expected_generation: int = 0) -> int:
        # the session registers lie outside the command block: written first, the command write then executes
        m = self.map
        lo, count = m.block("holding", "command_nonce", "command_expected_generation")
        words = [0] * count
        for name, value in (("command_nonce", nonce), ("command_expected_generation", expected_generation)):
            reg = m[name]
            words[reg.address - lo : reg.address - lo + reg.width] = mm.to_registers(reg, value)
        self._write(lo, words)
        return self._command(MsgType.COMMIT, crc32=crc32)

    def _read_table(self, prefix: str, command: MsgType, bank: TableBank) -> ParamTable:
        m = self.map
        lo, _ = m.block("input", f"{prefix}_nak_code", f"{prefix}_{PARAM_FIELDS[-1]}")
        w = self._read_block(prefix)
        code = int(self._get(w, lo, f"{prefix}_nak_code"))
        if code:
            raise CommandRefused(int(command), code, "")
        first = m[f"{prefix}_{PARAM_FIELDS[0]}"].address - lo
        self.stats.rx_messages += 1
        return ParamTable(
            bank=bank,
            generation=int(self._get(w, lo, "active_generation")) if prefix == "active" else 0,
            crc32=int(self._get(w, lo, f"{prefix}_crc32")),
            table=mm.table_from_registers(w[first : first + 2 * N_FIELDS]),
        )

    def read_staged(self) -> ParamTable:
        return self._read_table("staged", MsgType.READ_STAGED, TableBank.STAGED)

    def read_active(self) -> ParamTable:
        return self._read_table("active", MsgType.READ_ACTIVE, TableBank.ACTIVE)

    def read_estimate(self) -> Estimate:
        lo, _ = self.map.block("input", "estimate_nak_code", f"sigma_{ESTIMATE_FIELDS[-1]}")
        w = self._read_block("estimate")
        code = int(self._get(w, lo, "estimate_nak_code"))
        if code:
            raise CommandRefused(int(MsgType.READ_ESTIMATE), code, "")
        self.stats.rx_messages += 1
        return Estimate(
            status=int(self._get(w, lo, "estimate_status")),
            estimated_mask=int(self._get(w, lo, "estimate_mask")),
            base_generation=int(self._get(w, lo, "estimate_base_generation")),
            n_updates=int(self._get(w, lo, "estimate_updates")),
            last_frame=int(self._get(w, lo, "estimate_last_frame")),
            values=tuple(float(self._get(w, lo, f"estimate_{f}")) for f in ESTIMATE_FIELDS),
            sigma=tuple(float(self._get(w, lo, f"sigma_{f}")) for f in ESTIMATE_FIELDS),
        )

    # ------------------------------------------------------------------------------------------ stream
    def recv_frame(self, timeout_s: float | None = None) -> CentroidFrame | None:
        if self._ended:
            return None
        timeout_s = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + timeout_s
        base = self._window_first
        head_count = (self._star_first - base) + self._stars_in_head * self._star_stride
        while True:
            head, words, state, n = self._read_window(base, head_count, deadline, timeout_s)
            seq = int(self._get(head, base, "window_seq"))
            if seq != self._last_seq or state == _WINDOW_END:
                break
            # the window delivered last time, again: our release did not take (Modbus TCP has no checksum, so a
            # release whose value was corrupted on the way up is answered like a good one). Release it again; the
            # frame is not delivered twice, nor counted as 2**32 - 1 lost.
            self.stats.corrupt_frames += 1
            self._release(seq, deadline)
        if state == _WINDOW_END:
            self._release(seq, deadline)
            self._count_loss(seq)
            self._ended = True
            return None
        self._release(seq, deadline)
        # counted only once the window is released: if a read or the release fails, the next poll sees the same
        # window_seq again, and that is the same message, not 2**32 - 1 lost ones
        self._count_loss(seq)
        frame = self._decode_frame(np.asarray(words, dtype=np.int64), base, n)
        self.stats.rx_messages += 1
        return frame

    def _read_window(self, base: int, head_count: int, deadline: float, timeout_s: float) -> tuple:
        """The stream window, read until intact (a frame or the end of the stream): (head, words, state, n)."""
        block = self._window_block
        while True:
            head = self._read("input", base, head_count, deadline)
            state = self._get(head, base, "window_state")
            if state in (_WINDOW_FRAME, _WINDOW_END):
                n = mm.block_n_stars(block, head, base) if state == _WINDOW_FRAME else 0
                words = head
                if n > self._stars_in_head and n <= block.stars_from.count:
                    more_from = base + len(head)
                    words = head + self._read("input", more_from, block.read_span(n)[1] - len(head), deadline)
                if mm.block_intact(block, words, base):  # (false for a star count beyond the window, too)
                    break
                self.stats.corrupt_frames += 1  # a window corrupted on the way: read it again
            elif time.monotonic() >= deadline:
                raise LinkError(f"{self.name}: no centroid frame within {timeout_s:g} s")
            else:
                time.sleep(_POLL_S)
            if time.monotonic() >= deadline:
                raise LinkError(f"{self.name}: no intact centroid frame within {timeout_s:g} s")
        return head, words, state, n

    def _count_loss(self, seq: int) -> None:
        if self._last_seq is not None:
            self.stats.lost_messages += (seq - self._last_seq - 1) % (1 << 32)
        self._last_seq = seq

    def _release(self, seq: int, deadline: float | None = None) -> None:
        reg = self.map["stream_ack_seq"]
        self._write(reg.address, mm.to_registers(reg, seq), deadline=deadline)  # idempotent: releases seq only

    def _decode_frame(self, words: np.ndarray, base: int, n: int) -> CentroidFrame:
        x_reg, y_reg, id_reg, mag_reg = self._star_regs
        return CentroidFrame(
            frame=int(self._get(list(words[: self._star_first - base]), base, "window_frame")),
            t_us=int(self._get(list(words[: self._star_first - base]), base, "window_t_us")),
            star_id=mm.array_raw(words, id_reg, n, base).astype(np.uint32),
            x_px=dequantise_px(mm.array_raw(words, x_reg, n, base)),
            y_px=dequantise_px(mm.array_raw(words, y_reg, n, base)),
            mag=dequantise_mag(mm.array_raw(words, mag_reg, n, base)),
        )

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._client.close()
