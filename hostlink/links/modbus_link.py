"""Modbus link: the sensor's commands as register reads and writes laid out by ``protocol/modbus_map.json``; all
pymodbus calls go through ``hostlink.links.modbus_adapter``.

Link strings:

* ``modbus-tcp:HOST:PORT[,unit=N]`` -- Modbus TCP (what ``hostlink emulate --transport modbus`` prints as ``link``);
* ``modbus-rtu:tcp://HOST:PORT[,unit=N]`` -- RTU framing over TCP (an RS-485 gateway; the emulator's ``link_rtu``);
* ``modbus-rtu:/dev/ttyUSB0[@BAUD][,unit=N,parity=E]`` -- RTU on a serial line (default 19200 baud, even parity).

``unit`` defaults to the map's ``unit_id`` (1). A command is one write of the argument registers and ``command``
(function code 16), then one read of the ``result_*`` registers; a NAK becomes :class:`CommandRefused` with the
sensor's code and text. The stream is polled: read the window, release it with ``stream_ack_seq``; lost messages are
counted from gaps in ``window_seq``.
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


def parse_target(scheme: str, target: str) -> dict:
    """Keyword arguments of :class:`RegisterClient` for a link string; one-line UserError if malformed."""
    usage = (
        f"--link {scheme}:{target}: expected modbus-tcp:HOST:PORT[,unit=N], modbus-rtu:tcp://HOST:PORT[,unit=N] "
        "or modbus-rtu:/dev/ttyUSB0[@BAUD][,unit=N,parity=E]"
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
        client = RegisterClient(timeout_s=timeout_s, **kw)
    except ModbusAdapterError as exc:
        raise LinkError(f"{scheme}:{target}: {exc}") from None
    return ModbusLink(client, f"{scheme}:{target}", timeout_s)


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

    # ------------------------------------------------------------------------------------ register I/O
    def _read(self, table: str, address: int, count: int) -> list[int]:
        self._check_open()
        out: list[int] = []
        try:
            while count > 0:
                n = min(count, mm.MAX_READ_REGISTERS)
                out += self._client.read(table, address, n)
                address, count = address + n, count - n
        except ModbusAdapterError as exc:
            raise LinkError(f"{self.name}: {exc}") from None
        self.stats.rx_bytes += 2 * len(out)
        return out

    def _write(self, address: int, values: list[int]) -> None:
        self._check_open()
        try:
            self._client.write(address, values)
        except ModbusAdapterError as exc:
            raise LinkError(f"{self.name}: {exc}") from None
        self.stats.tx_bytes += 2 * len(values)

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
        self._write(lo, words)
        rlo, rcount = self._result_block
        res = self._read("input", rlo, rcount)
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
        lo, count = self._status_block
        w = self._read("input", lo, count)
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

    def stage_begin(self, length: int) -> None:
        self._command(MsgType.STAGE_BEGIN, arg=length)

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

    def commit(self, crc32: int) -> int:
        return self._command(MsgType.COMMIT, crc32=crc32)

    def _read_table(self, prefix: str, command: MsgType, bank: TableBank) -> ParamTable:
        m = self.map
        lo, count = m.block("input", f"{prefix}_nak_code", f"{prefix}_{PARAM_FIELDS[-1]}")
        w = self._read("input", lo, count)
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
        lo, count = self.map.block("input", "estimate_nak_code", f"sigma_{ESTIMATE_FIELDS[-1]}")
        w = self._read("input", lo, count)
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
        while True:
            head = self._read("input", base, (self._star_first - base) + self._stars_in_head * self._star_stride)
            state = self._get(head, base, "window_state")
            if state in (_WINDOW_FRAME, _WINDOW_END):
                break
            if time.monotonic() >= deadline:
                raise LinkError(f"{self.name}: no centroid frame within {timeout_s:g} s")
            time.sleep(_POLL_S)
        seq = int(self._get(head, base, "window_seq"))
        if state == _WINDOW_END:
            self._release(seq)
            self._count_loss(seq)
            self._ended = True
            return None
        n = int(self._get(head, base, "window_n_stars"))
        words = head
        if n > self._stars_in_head:
            more_from = base + len(head)
            words = head + self._read("input", more_from, self._star_first + n * self._star_stride - more_from)
        self._release(seq)
        # counted only once the window is released: if a read or the release fails, the next poll sees the same
        # window_seq again, and that is the same message, not 2**32 - 1 lost ones
        self._count_loss(seq)
        frame = self._decode_frame(np.asarray(words, dtype=np.int64), base, n)
        self.stats.rx_messages += 1
        return frame

    def _count_loss(self, seq: int) -> None:
        if self._last_seq is not None:
            self.stats.lost_messages += (seq - self._last_seq - 1) % (1 << 32)
        self._last_seq = seq

    def _release(self, seq: int) -> None:
        reg = self.map["stream_ack_seq"]
        self._write(reg.address, mm.to_registers(reg, seq))

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
