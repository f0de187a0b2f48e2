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
``stream_ack_seq``; lost messages are counted from gaps in ``window_seq``. Each poll reads the window's fixed
registers and their check first, and the rest only when they hold a message.

Integrity and recovery: every block read as a snapshot (result, status, tables, estimate, stream window) carries a
CRC-32 check register (``checked_blocks`` in the map); a block whose check fails is read again, never decoded. An
exchange that fails on the way (timeout, garbled or short answer) is counted in ``stats.corrupt_frames`` and made again
(on a fresh connection when no answer came: a request that lost a byte must not take the next one down with it)
until the link timeout has passed without an answer; then one LinkError (the link is gone). Each exchange waits for its
answer as long as :class:`AnswerTimer` says (the line time plus the device's response time as measured, like TCP's
retransmission timeout), so a lost answer costs the device's usual response time, and reads are as long as the line's
measured byte fault rate makes fastest (:meth:`AnswerTimer.read_registers`). Command writes are repeated only for
commands that may run twice (STREAM_CONTROL, STAGE_CHUNK, STAGE_VERIFY); STAGE_BEGIN and COMMIT are written again only
when ``result_counter`` shows they did not run.
"""

from __future__ import annotations

import time

import numpy as np

from hostlink.errors import LinkError, UserError
from hostlink.links.base import DEFAULT_TIMEOUT_S, CommandRefused, Link
from hostlink.links.modbus_adapter import ModbusAdapterError, RegisterClient
from hostlink.links.urlhandler import refuse_file_writing_url
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
_WINDOW_EMPTY, _WINDOW_FRAME, _WINDOW_END = 0, 1, 2
#: A device's time to answer on top of the line time [s] (Modbus over serial line v1.02: a slave answers within
#: its response timeout, typically 100 ms or less; TCP on a LAN well under that): the longest an exchange waits,
#: and its wait until answers have been timed (``response_timeout_ms`` in the link string sets it).
_ANSWER_LATENCY_S = 0.2
#: Shortest wait for an answer on top of its line time [s]: a few scheduler ticks of the host (Linux: 1-4 ms), so
#: that a host busy with other work seldom times out answers that are on their way (one that it does is asked for
#: again, like a lost one).
_MIN_WAIT_S = 0.01
#: Timeouts in a row before the wait doubles: on a noisy line most timeouts are lost bytes, not a slow device, and
#: doubling at each of them (TCP's rule, made for congestion) would multiply the cost of every loss; a device slower
#: than the wait still gets its full response time after a few tries.
_TIMEOUTS_BEFORE_BACKOFF = 2
#: Longest one exchange is tried while damaged answers keep arriving [link timeouts]: at 1 % byte drops a 40-register
#: read fails with probability ~0.6, so 10 s of failures in a row (~500 tries) does not happen; a device whose every
#: answer is malformed still ends in one LinkError.
_PATIENCE_TIMEOUTS = 5
#: Pause before an exchange is made again after a failure that came at once (a refused connection: do not spin) [s].
_RETRY_PAUSE_S = 0.005
#: Failed exchanges in a row after which the connection is opened again when answers (even damaged) did come: the
#: bytes of a failed answer are read and dropped within its own exchange, so the next one starts clean unless an
#: answer came late or cut short; a second failure in a row resynchronises (a TCP handshake, not after every loss).
#: An exchange that got no byte back reopens at once: its request may have lost a byte on the way up, leaving the
#: device's framer waiting for it (Modbus TCP's length field, RTU's frame), and the next request on that connection
#: would complete the broken one and be lost with it (with faults host -> sensor that doomed try ended 1 of 2 runs
#: of link_faults.py --both-directions in a LinkError).
_RESET_AFTER_FAILURES = 2
#: Smallest read on a noisy line [registers] (the read size is chosen by AnswerTimer.read_registers).
_MIN_CHUNK = 8
#: Bytes of a read's request and answer around its registers (Modbus TCP: 12-byte request, 9-byte answer header;
#: RTU: 8 and 5), the larger, so a read's exposure to byte faults is not underestimated.
_EXCHANGE_OVERHEAD_BYTES = 21
#: Weight kept by the estimate of the line's byte fault rate at each exchange (memory of ~50 exchanges).
_FAULT_MEMORY = 0.98
#: Reads in a row of a checked block whose check fails before the link gives up (a device that answers but with
#: another register layout). On a line with BER 1e-4 a 300-byte block fails its check with probability 0.21 (Modbus
#: TCP has no checksum of its own), so 64 failures in a row happen with probability 0.21**64 < 1e-43.
_MAX_CHECK_FAILURES = 64
#: Bits per byte of an RTU character (start, 8 data, parity or a second stop bit, stop: Modbus over serial line
#: v1.02, 2.5.1).
_RTU_BITS_PER_BYTE = 11
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
        refuse_file_writing_url(port, f"--link {scheme}:")  # pymodbus opens the port with pyserial's serial_for_url
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
    response_s = kw.pop("response_timeout_s", None)
    timer = AnswerTimer(_ANSWER_LATENCY_S if response_s is None else response_s, kw.get("baud"))
    try:
        client = RegisterClient(timeout_s=timer.wait_s(mm.MAX_READ_REGISTERS), **kw)
    except ModbusAdapterError as exc:
        raise LinkError(f"{scheme}:{target}: {exc}") from None
    return ModbusLink(client, f"{scheme}:{target}", timeout_s, timer=timer)


class AnswerTimer:
    """How long one Modbus exchange waits for its answer: the line time of the request and the answer (11-bit
    characters at ``baud`` on a serial line; none on TCP) plus the device's response time, estimated from the
    answers timed so far as the retransmission timeout of TCP (RFC 6298: smoothed time SRTT and variation RTTVAR with
    gains 1/8 and 1/4, wait SRTT + 4 RTTVAR, doubled after timeouts in a row), between _MIN_WAIT_S and ``response_s``
    (the device's longest response time, which is also the wait before the first answer was timed).

    A lost answer then costs about the device's usual response time, not its worst one, and the link asks again;
    an answer later than the wait is a failed exchange like a lost one (asked again, never taken for the next one:
    the connection is reset and the answers' transaction id, address and count are checked)."""

    def __init__(self, response_s: float = _ANSWER_LATENCY_S, baud: int | None = None) -> None:
        self.response_s = float(response_s)
        self.baud = baud
        self.srtt_s: float | None = None
        self.rttvar_s = 0.0
        self.rto_s = self.response_s
        self._timeouts = 0  # in a row
        self._failed_w = 0.0  # failed exchanges and bytes exchanged, exponentially weighted (_FAULT_MEMORY)
        self._bytes_w = 0.0

    def exchanged(self, registers: int, ok: bool) -> None:
        """Count one exchange of ``registers`` (read or written) for the line's byte fault rate."""
        self._failed_w = _FAULT_MEMORY * self._failed_w + (0.0 if ok else 1.0)
        self._bytes_w = _FAULT_MEMORY * self._bytes_w + _EXCHANGE_OVERHEAD_BYTES + 2 * registers

    def byte_fault_rate(self) -> float:
        """Estimated probability that a byte is lost or corrupted: failed exchanges per byte exchanged (the rate
        of a Poisson count; for the small rates where it matters, 1 - (1 - e)**b ~ e b per exchange of b bytes)."""
        return self._failed_w / self._bytes_w if self._bytes_w else 0.0

    def read_registers(self) -> int:
        """The read size that takes the least time per register at the estimated byte fault rate e: a read of n
        registers arrives whole with probability p = (1 - e)**(overhead + 2 n); it costs the answer time when it
        does and 1/p - 1 failed tries (each a full wait) on average before, so the expected time per register is
        (t_answer + (1/p - 1) t_wait) / n, minimised over n (a clean line: the largest read Modbus allows)."""
        e = self.byte_fault_rate()
        if e <= 0.0:
            return mm.MAX_READ_REGISTERS
        n = np.arange(_MIN_CHUNK, mm.MAX_READ_REGISTERS + 1)
        p = np.exp((_EXCHANGE_OVERHEAD_BYTES + 2 * n) * np.log1p(-min(e, 0.5)))
        line = np.array([self.line_s(int(k)) for k in (n[0], n[-1])])
        line_n = line[0] + (n - n[0]) * (line[1] - line[0]) / (n[-1] - n[0])  # the line time is linear in n
        t_answer = (self.srtt_s or 0.0) + line_n
        t_wait = self.rto_s + line_n + _RETRY_PAUSE_S
        return int(n[np.argmin((t_answer + (1.0 / p - 1.0) * t_wait) / n)])

    def line_s(self, answer_registers: int, request_registers: int = 0) -> float:
        """Line time of a request carrying ``request_registers`` and an answer carrying ``answer_registers`` [s]
        (RTU: address, function, byte count or address and count, the registers, CRC-16)."""
        if not self.baud:
            return 0.0
        return (9 + 2 * request_registers + 5 + 2 * answer_registers) * _RTU_BITS_PER_BYTE / self.baud

    def wait_s(self, answer_registers: int, request_registers: int = 0) -> float:
        return self.line_s(answer_registers, request_registers) + self.rto_s

    def answered(self, elapsed_s: float, answer_registers: int, request_registers: int = 0) -> None:
        """An answer came after ``elapsed_s`` (request sent to answer parsed)."""
        self._timeouts = 0
        sample = max(0.0, elapsed_s - self.line_s(answer_registers, request_registers))
        if self.srtt_s is None:
            self.srtt_s, self.rttvar_s = sample, sample / 2
        else:
            self.rttvar_s = 0.75 * self.rttvar_s + 0.25 * abs(self.srtt_s - sample)
            self.srtt_s = 0.875 * self.srtt_s + 0.125 * sample
        self.rto_s = min(self.response_s, max(_MIN_WAIT_S, self.srtt_s + 4 * self.rttvar_s))

    def timed_out(self) -> None:
        """No answer within the wait: after _TIMEOUTS_BEFORE_BACKOFF in a row, wait twice as long next time, up to
        the device's longest response time."""
        self._timeouts += 1
        if self._timeouts >= _TIMEOUTS_BEFORE_BACKOFF:
            self.rto_s = min(self.response_s, 2 * self.rto_s)


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
        timer: AnswerTimer | None = None,
    ) -> None:
        super().__init__()
        self.name = name
        self.timer = timer or AnswerTimer()
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

    # ------------------------------------------------------------------------------------ register I/O
    def _read(self, table: str, address: int, count: int) -> list[int]:
        """``count`` registers from ``address``, in reads of at most the current chunk size; a read that fails on the
        way (timeout, garbled or short answer) is counted in ``stats.corrupt_frames`` and made again, with smaller
        chunks, until the link timeout has passed without an answer (then LinkError: the link is gone)."""
        self._check_open()
        out: list[int] = []
        while len(out) < count:
            at = address + len(out)
            # the chunk size is read at each try: a read made again after a failure asks for fewer registers
            left = count - len(out)
            out += self._attempt(
                lambda n, _req, at=at: self._client.read(table, at, n),
                lambda left=left: (min(left, self.timer.read_registers()), 0),
            )
        self.stats.rx_bytes += 2 * len(out)
        return out

    def _write(self, address: int, values: list[int], retry: bool = True) -> None:
        """Write holding registers; ``retry``: the write may be made again after a failure on the way (it must be
        idempotent: a command that could run twice is written once, and a failure raises LinkError)."""
        self._check_open()
        self._attempt(lambda _ans, _req: self._client.write(address, values), lambda: (0, len(values)), retry=retry)
        self.stats.tx_bytes += 2 * len(values)

    def _attempt(  # noqa: ANN202 - the client call's result
        self,
        exchange,  # noqa: ANN001 - a client call of (answer registers, request registers)
        size,  # noqa: ANN001 - () -> (answer registers, request registers) of the next try
        retry: bool = True,
        patient: bool = False,
    ):
        """One Modbus exchange, each try waiting for its answer as long as :class:`AnswerTimer` says (``patient``:
        the device's longest response time), made again after failures on the way until the link timeout has passed
        since the first try or the last damaged answer, whichever is later (then LinkError, the link is gone; at once
        if not ``retry``): a device whose answers arrive, even damaged, is there. A Modbus exception answer is asked
        again too: on a noisy line it may be a corrupted answer (Modbus TCP has no checksum)."""
        start = heard = time.monotonic()
        failures = 0
        while True:
            answer_registers, request_registers = size()
            wait_s = self.timer.wait_s(answer_registers, request_registers)
            if patient:
                wait_s = self.timer.line_s(answer_registers, request_registers) + self.timer.response_s
            self._client.set_answer_timeout(wait_s)
            t0 = time.monotonic()
            try:
                result = exchange(answer_registers, request_registers)
            except ModbusAdapterError as exc:
                now = time.monotonic()
                if exc.answered and exc.exception_code is None:
                    heard = now  # the device answered, the answer was damaged on the way: it is there
                elif now - t0 >= wait_s:
                    self.timer.timed_out()  # nothing came: perhaps a device slower than the wait
                silent_s = now - max(start, heard)  # since the first try or the last damaged answer
                if not retry or max(silent_s, (now - start) / _PATIENCE_TIMEOUTS) >= self.timeout_s:
                    raise LinkError(f"{self.name}: {exc}") from None
                self.stats.corrupt_frames += 1
                self.timer.exchanged(answer_registers + request_registers, ok=False)
                failures += 1
                if not exc.answered or failures % _RESET_AFTER_FAILURES == 0:
                    # resynchronise: late or partial bytes of failed exchanges must not be taken for the next answer
                    self._client.reset()
                if now - t0 < wait_s and not exc.answered:
                    time.sleep(_RETRY_PAUSE_S)  # it failed at once (a refused connection): do not spin
                continue
            self.timer.answered(time.monotonic() - t0, answer_registers, request_registers)
            self.timer.exchanged(answer_registers + request_registers, ok=True)
            return result

    def _read_block(self, name: str) -> list[int]:
        """The registers of a checked block (``protocol/modbus_map.json`` ``checked_blocks``), read again until its
        check matches (each mismatch counted in ``stats.corrupt_frames``; LinkError after _MAX_CHECK_FAILURES in a
        row, or when a read finds the link gone)."""
        block = self.map.checked_block(name)
        for _ in range(_MAX_CHECK_FAILURES):
            lo, count = block.read_span()
            words = self._read("input", lo, count)
            if mm.block_intact(block, words, lo):
                return words
            self.stats.corrupt_frames += 1
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
        if msg_type in _IDEMPOTENT:
            self._write(lo, words)
        else:
            self._write_once(lo, words, msg_type)
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

    def _write_once(self, address: int, words: list[int], msg_type: MsgType) -> None:
        """Write a command that must not run twice (STAGE_BEGIN, COMMIT). Each try waits the device's longest
        response time for its answer (a late answer would make a second try run it twice); when the answer is lost
        the sensor's ``result_counter`` (commands run so far) tells whether the command ran: not yet, it is written
        again; once, with its result in place, it is done; anything else (another host's command in between) is a
        LinkError, the upload not completed."""
        self._check_open()
        rlo, _ = self._result_block
        before = int(self._get(self._read_block("result"), rlo, "result_counter"))
        start = time.monotonic()
        while True:
            try:
                self._attempt(
                    lambda _ans, _req: self._client.write(address, words),
                    lambda: (0, len(words)),
                    retry=False,
                    patient=True,
                )
                break
            except LinkError:
                if time.monotonic() - start >= self.timeout_s:
                    raise
            self.stats.corrupt_frames += 1
            self._client.reset()
            res = self._read_block("result")
            ran = (int(self._get(res, rlo, "result_counter")) - before) % (1 << 16)
            if ran == 1 and self._get(res, rlo, "result_command") == int(msg_type):
                break  # it ran; only its answer was lost
            if ran != 0:
                raise LinkError(
                    f"{self.name}: the answer to {msg_type.name} was lost and the sensor ran {ran} command(s) since "
                    "(another host?): the upload is not completed"
                )
        self.stats.tx_bytes += 2 * len(words)

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
        if enable:
            # a stream left running is stopped first, so that the enable starts a new one: its window_seq numbers
            # start at 1, and every message lost from the stream's start is counted
            self._command(MsgType.STREAM_CONTROL, arg=0)
        self._command(MsgType.STREAM_CONTROL, arg=1 if enable else 0)
        self._ended = False
        if enable:
            self._last_seq = 0
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
        """The next stream message. ``timeout_s`` bounds the wait for the sensor to put a message in its window;
        reads that fail on the way are asked again (the window holds its message until released), each until the
        link timeout has passed without an answer."""
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
            self._release(seq)
        if state == _WINDOW_END:
            self._release(seq)
            self._count_loss(seq)
            self._ended = True
            return None
        self._release(seq)
        # counted only once the window is released: if a read or the release fails, the next poll sees the same
        # window_seq again, and that is the same message, not 2**32 - 1 lost ones
        self._count_loss(seq)
        frame = self._decode_frame(np.asarray(words, dtype=np.int64), base, n)
        self.stats.rx_messages += 1
        return frame

    def _read_window(self, base: int, head_count: int, deadline: float, timeout_s: float) -> tuple:
        """The stream window, read until intact (a frame or the end of the stream): (head, words, state, n).
        LinkError when a read begun at ``deadline`` or later finds it empty, intact (the sensor had ``timeout_s`` to
        fill it; the time a noisy line takes to answer is not counted against it), or when it fails its check
        _MAX_CHECK_FAILURES times in a row.

        Each poll reads the block's fixed registers and their check first (one chunk on a noisy line): an empty
        window is judged by them alone, and only one that holds a message is read on. A state that fails the check
        is a read damaged on the way, read again (Modbus TCP has no checksum: a frame's state flipped to "empty"
        is not an empty window). Before, every poll read the whole head, and a damaged or empty one judged against
        the clock after all its chunks arrived ended a stream whose sensor was streaming, "no centroid frame within
        2 s", at three times the default fault rates (docs/links.md)."""
        block = self._window_block
        header = block.read_span(0)[1]  # the fixed registers and their check
        failures = 0
        while True:
            started = time.monotonic()
            head = self._read("input", base, min(head_count, max(header, self.timer.read_registers())))
            state = self._get(head, base, "window_state")
            if state == _WINDOW_EMPTY and mm.block_intact(block, head, base):
                if started >= deadline:
                    raise LinkError(f"{self.name}: no centroid frame within {timeout_s:g} s")
                time.sleep(_POLL_S)
                continue
            if state in (_WINDOW_FRAME, _WINDOW_END):
                if len(head) < head_count:
                    head = head + self._read("input", base + len(head), head_count - len(head))
                n = mm.block_n_stars(block, head, base) if state == _WINDOW_FRAME else 0
                words = head
                if n > self._stars_in_head and n <= block.stars_from.count:
                    more_from = base + len(head)
                    words = head + self._read("input", more_from, block.read_span(n)[1] - len(head))
                if mm.block_intact(block, words, base):  # (false for a star count beyond the window, too)
                    return head, words, state, n
            self.stats.corrupt_frames += 1  # a window damaged on the way: read it again
            failures += 1
            if failures >= _MAX_CHECK_FAILURES:
                raise LinkError(f"{self.name}: no intact centroid frame in {failures} reads of the window")

    def _count_loss(self, seq: int) -> None:
        if self._last_seq is not None:
            self.stats.lost_messages += (seq - self._last_seq - 1) % (1 << 32)
        self._last_seq = seq

    def _release(self, seq: int) -> None:
        reg = self.map["stream_ack_seq"]
        self._write(reg.address, mm.to_registers(reg, seq))  # idempotent: releases seq only

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
