"""Modbus endpoint of the emulated sensor: the register map (``protocol/modbus_map.json``) served on 127.0.0.1, over
Modbus TCP and over RTU framing on TCP (two ports, one register image), through ``hostlink.emulator.modbus_server``.

``hostlink emulate --transport modbus`` prints ``{"link": "modbus-tcp:127.0.0.1:PORT", "link_rtu":
"modbus-rtu:tcp://127.0.0.1:PORT2", ...}``. The layout comes from the map file alone:

* holding registers: the staging mailbox (``stage_*``), the command arguments and the ``command`` register -- a write
  that reaches ``command`` is turned into the protocol command and decided by the firmware before the write is
  answered; its ACK/NAK lands in the ``result_*`` input registers;
* input registers: refreshed from the firmware when read -- status (GET_STATUS), the active and staged sets
  (READ_ACTIVE, READ_STAGED), the estimate (READ_ESTIMATE) and the stream window;
* stream window: the oldest stream message not yet released (``stream_ack_seq``), numbered by ``window_seq``. The
  emulated sensor takes its next exposure when the host has released the window (a sensor with a deep FIFO that
  the host drains), so nothing is lost unless ``--drop-every`` says so.

This module decides nothing about parameters: every command goes to ``sensor.handle``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from hostlink.emulator.modbus_server import RegisterServer
from hostlink.emulator.sensor import EmulatedSensor, EndpointOptions
from hostlink.errors import UserError
from hostlink.links.modbus_adapter import ILLEGAL_ADDRESS, ILLEGAL_VALUE, ModbusAdapterError
from protocol import modbus_map as mm
from protocol.messages import (
    ESTIMATE_FIELDS,
    MAX_STARS,
    Ack,
    CentroidFrame,
    Commit,
    EndOfStream,
    Estimate,
    GetStatus,
    Message,
    MsgType,
    Nak,
    ParamTable,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    Telemetry,
    nak_text_bytes,
    quantise_mag,
    quantise_px,
)
from protocol.param_table import N_FIELDS, PARAM_FIELDS, TABLE_BYTES

RESULT_NONE, RESULT_ACK, RESULT_NAK = 0, 1, 2
WINDOW_EMPTY, WINDOW_FRAME, WINDOW_END = 0, 1, 2


def _group(m: mm.ModbusMap, table: str, prefixes: tuple[str, ...]) -> tuple[int, int]:
    regs = [r for r in m.table(table) if r.name.startswith(prefixes)]
    return min(r.address for r in regs), max(r.address + r.span for r in regs)


def _address_range(address: int, count: int) -> tuple[int, int]:
    return address, address + count


class RegisterSensor:
    """The register image of the sensor and its translation to and from protocol messages."""

    def __init__(self, sensor: EmulatedSensor, drop_every: int = 0, regmap: mm.ModbusMap | None = None) -> None:
        self.sensor = sensor
        self.map = regmap or mm.load_map()
        self.drop_every = int(drop_every)
        self.holding = [0] * self.map.table_size("holding")
        self.inputs = [0] * self.map.table_size("input")
        self._lock = threading.RLock()  # the TCP and RTU servers share this image
        self._result_counter = 0
        self._stream_seq = 0
        self._window: list[int] | None = None  # registers of window_* when a message is held
        self._window_seq: int | None = None
        m = self.map
        self._stage = m.block("holding", f"stage_{PARAM_FIELDS[0]}", f"stage_{PARAM_FIELDS[-1]}")
        self._command_addr = m["command"].address
        self._ack_addr = m["stream_ack_seq"].address
        self._refreshers: list[tuple[tuple[int, int], Callable[[], None]]] = [
            (_group(m, "input", ("status_",)), self._refresh_status),
            (_group(m, "input", ("active_",)), self._refresh_active),
            (_group(m, "input", ("staged_",)), self._refresh_staged),
            (_group(m, "input", ("estimate_", "sigma_")), self._refresh_estimate),
            (_group(m, "input", ("window_",)), self._refresh_window),
        ]
        self._window_span = _group(m, "input", ("window_",))
        #: each checked block with the widest address range it can span (all MAX_STARS stars)
        self._checked = [(b, _address_range(*b.read_span(MAX_STARS))) for b in m.checked_blocks]
        self.commands = {c["code"]: c["name"] for c in m.commands}

    # ------------------------------------------------------------------------------------ server hooks
    def on_read(self, table: str, address: int, count: int) -> list[int]:
        with self._lock:
            if table == "holding":
                return self.holding[address : address + count]
            for (lo, hi), refresh in self._refreshers:
                if address < hi and address + count > lo:
                    refresh()
            for block, (lo, hi) in self._checked:
                if address < hi and address + count > lo:
                    mm.seal_block(block, self.inputs)  # the check of what is in the image now
            return self.inputs[address : address + count]

    def on_write(self, address: int, values: list[int]) -> None:
        with self._lock:
            end = address + len(values)
            if address < 0 or end > len(self.holding):
                raise ModbusAdapterError("outside the holding registers", ILLEGAL_ADDRESS)
            self.holding[address:end] = values
            ack = self.map["stream_ack_seq"]
            if address <= ack.address and end >= ack.address + ack.width:
                self._release_window(mm.get(self.holding, ack))
            if address <= self._command_addr < end:
                self._execute(self.holding[self._command_addr])

    # ---------------------------------------------------------------------------------------- commands
    def _execute(self, code: int) -> None:
        m, h = self.map, self.holding
        arg = mm.get(h, m["command_arg"])
        crc = mm.get(h, m["command_crc32"])
        if code == MsgType.STREAM_CONTROL:
            cmd: Message = StreamControl(enable=bool(arg))
        elif code == MsgType.STAGE_BEGIN:
            cmd = StageBegin(length=arg)
        elif code == MsgType.STAGE_CHUNK:
            length = mm.get(h, m["command_length"])
            if arg + length > TABLE_BYTES:
                raise ModbusAdapterError("chunk outside the staging mailbox", ILLEGAL_VALUE)
            lo, hi = self._stage
            table = mm.table_from_registers(h[lo:hi])
            cmd = StageChunk(offset=arg, data=table[arg : arg + length])
        elif code == MsgType.STAGE_VERIFY:
            cmd = StageVerify(crc32=crc)
        elif code == MsgType.COMMIT:
            cmd = Commit(
                crc32=crc,
                nonce=mm.get(h, m["command_nonce"]),
                expected_generation=mm.get(h, m["command_expected_generation"]),
            )
        else:
            raise ModbusAdapterError(f"command code {code} is not in the register map", ILLEGAL_VALUE)
        started = self.sensor.streams_started
        reply = self.sensor.handle(cmd)
        if self.sensor.streams_started != started:
            # a new stream starts with a fresh exposure, its messages numbered from 1 (window_seq 0 = none yet); a
            # repeated enable while the stream runs keeps the window, so the frame in it is not lost
            self._window, self._window_seq, self._stream_seq = None, None, 0
        self._set_result(code, reply)

    def _set_result(self, code: int, reply: Message) -> None:
        m, i = self.map, self.inputs
        self._result_counter = (self._result_counter + 1) & 0xFFFF
        mm.put(i, m["result_command"], code)
        mm.put(i, m["result_counter"], self._result_counter)
        if isinstance(reply, Nak):
            mm.put(i, m["result_status"], RESULT_NAK)
            mm.put(i, m["result_code"], reply.code)
            mm.put(i, m["result_value"], 0)
            mm.put(i, m["result_text"], nak_text_bytes(reply.text).decode("utf-8"))
        else:
            mm.put(i, m["result_status"], RESULT_ACK)
            mm.put(i, m["result_code"], 0)
            mm.put(i, m["result_value"], reply.value if isinstance(reply, Ack) else 0)
            mm.put(i, m["result_text"], "")

    # ----------------------------------------------------------------------------------------- queries
    def _refresh_status(self) -> None:
        t = self.sensor.handle(GetStatus())
        if not isinstance(t, Telemetry):
            return
        m, i = self.map, self.inputs
        for name, value in (
            ("status_streaming", int(t.streaming)),
            ("status_stage_state", t.stage_state),
            ("status_active_generation", t.active_generation),
            ("status_active_crc32", t.active_crc32),
            ("status_frames_processed", t.frames_processed),
            ("status_last_frame", t.last_frame),
            ("status_estimator_updates", t.estimator_updates),
        ):
            mm.put(i, m[name], value)

    def _refresh_table(self, prefix: str, reply: Message) -> None:
        m, i = self.map, self.inputs
        first = m[f"{prefix}_{PARAM_FIELDS[0]}"].address
        if isinstance(reply, ParamTable):
            mm.put(i, m[f"{prefix}_nak_code"], 0)
            mm.put(i, m[f"{prefix}_crc32"], reply.crc32)
            if prefix == "active":
                mm.put(i, m["active_generation"], reply.generation)
            i[first : first + 2 * N_FIELDS] = mm.registers_from_table(reply.table)
        else:
            mm.put(i, m[f"{prefix}_nak_code"], reply.code if isinstance(reply, Nak) else 0xFFFF)
            mm.put(i, m[f"{prefix}_crc32"], 0)
            if prefix == "active":
                mm.put(i, m["active_generation"], 0)
            i[first : first + 2 * N_FIELDS] = [0] * (2 * N_FIELDS)

    def _refresh_active(self) -> None:
        self._refresh_table("active", self.sensor.handle(ReadActive()))

    def _refresh_staged(self) -> None:
        self._refresh_table("staged", self.sensor.handle(ReadStaged()))

    def _refresh_estimate(self) -> None:
        m, i = self.map, self.inputs
        e = self.sensor.handle(ReadEstimate())
        ok = isinstance(e, Estimate)
        mm.put(i, m["estimate_nak_code"], 0 if ok else (e.code if isinstance(e, Nak) else 0xFFFF))
        est = e if ok else Estimate()
        for name, value in (
            ("estimate_status", est.status),
            ("estimate_mask", est.estimated_mask),
            ("estimate_base_generation", est.base_generation),
            ("estimate_updates", est.n_updates),
            ("estimate_last_frame", est.last_frame),
        ):
            mm.put(i, m[name], value)
        for k, f in enumerate(ESTIMATE_FIELDS):
            mm.put(i, m[f"estimate_{f}"], est.values[k])
            mm.put(i, m[f"sigma_{f}"], est.sigma[k])

    # ------------------------------------------------------------------------------------------ stream
    def _release_window(self, seq: int) -> None:
        if self._window is not None and seq == self._window_seq:
            self._window, self._window_seq = None, None

    def _refresh_window(self) -> None:
        lo, hi = self._window_span
        if self._window is None:
            msg = self.sensor.next_stream_message()
            while msg is not None:
                self._stream_seq = (self._stream_seq + 1) & 0xFFFFFFFF
                if self.drop_every and self._stream_seq % self.drop_every == 0:
                    msg = self.sensor.next_stream_message()  # test hook: this message is lost
                    continue
                self._window = self._window_registers(msg, self._stream_seq)
                self._window_seq = self._stream_seq
                break
        self.inputs[lo:hi] = self._window if self._window is not None else [0] * (hi - lo)

    def _window_registers(self, msg: CentroidFrame | EndOfStream, seq: int) -> list[int]:
        m = self.map
        lo, hi = self._window_span
        w = [0] * (hi - lo)

        def put(name: str, value: int) -> None:
            reg = m[name]
            w[reg.address - lo : reg.address - lo + reg.width] = mm.to_registers(reg, value)

        put("window_seq", seq)
        if isinstance(msg, EndOfStream):
            put("window_state", WINDOW_END)
            put("window_frames_sent", msg.frames_sent)
            return w
        put("window_state", WINDOW_FRAME)
        put("window_n_stars", msg.n_stars)
        put("window_frame", msg.frame)
        put("window_t_us", msg.t_us)
        n = msg.n_stars
        if n:
            words = np.asarray(w, dtype=np.int64)
            for name, raw in (
                ("window_star_x_px", quantise_px(msg.x_px)),
                ("window_star_y_px", quantise_px(msg.y_px)),
                ("window_star_id", np.asarray(msg.star_id, dtype=np.int64)),
                ("window_star_mag", quantise_mag(msg.mag).astype(np.int64)),
            ):
                reg = m[name]
                idx = reg.address - lo + reg.stride * np.arange(n)
                value = raw.astype(np.int64) & ((1 << (16 * reg.width)) - 1)  # two's complement of the width
                for k in range(reg.width):
                    words[idx + k] = (value >> (16 * (reg.width - 1 - k))) & 0xFFFF
            w = [int(v) for v in words]
        return w


def serve(
    sensor: EmulatedSensor, options: EndpointOptions, ready: Callable[[dict], None], stop: threading.Event
) -> None:
    image = RegisterSensor(sensor, options.drop_every)
    sizes = dict(
        holding_size=len(image.holding),
        input_size=len(image.inputs),
        on_read=image.on_read,
        on_write=image.on_write,
        host=options.host,
        unit=options.unit,
    )
    rtu_port = int(options.extra.get("rtu_port", 0))
    try:
        tcp = RegisterServer(framing="tcp", port=options.port, **sizes).start()
        rtu = RegisterServer(framing="rtu", port=rtu_port, **sizes).start()
    except ModbusAdapterError as exc:
        raise UserError(f"cannot start the Modbus emulator: {exc}") from None
    try:
        ready(
            {
                "link": f"modbus-tcp:{options.host}:{tcp.port},unit={options.unit}",
                "link_rtu": f"modbus-rtu:tcp://{options.host}:{rtu.port},unit={options.unit}",
                "transport": "modbus",
                "port": tcp.port,
                "rtu_port": rtu.port,
                "unit": options.unit,
            }
        )
        stop.wait()
    finally:
        tcp.stop()
        rtu.stop()
