"""The only module that calls pymodbus (pinned to one minor release in pyproject.toml): a register client and a
register server, each a few methods wide, so a pymodbus upgrade touches this file alone.

* :class:`RegisterClient` -- Modbus TCP, RTU framing over TCP (an RS-485 gateway, or the emulator), or RTU on a
  serial port; ``read(table, address, count)``, ``write(address, values)``, ``close()``. Failures raise
  :class:`ModbusAdapterError` with one line (``exception_code`` set when the device answered with a Modbus exception).
* :class:`RegisterServer` -- a TCP server (MBAP or RTU framing) whose holding and input registers are served by two
  callbacks, ``on_read(table, address, count) -> list[int]`` and ``on_write(address, values)``; raising
  :class:`ModbusAdapterError` with an ``exception_code`` in a callback answers the request with that Modbus exception.
  It runs its own asyncio loop on a daemon thread.

pymodbus 3.16 facts this relies on (checked against its source): ``ModbusTcpServer`` takes a ``SimDevice`` whose async
``action`` sees every request before the datastore does (reads may fill ``current_registers``, writes happen after);
``ModbusTcpClient`` accepts ``framer=FramerType.RTU`` (RTU over TCP); request methods take ``device_id=``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

#: Modbus exception codes (Modbus application protocol v1.1b3, section 7).
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
_EXC = {
    ILLEGAL_FUNCTION: ExcCodes.ILLEGAL_FUNCTION,
    ILLEGAL_ADDRESS: ExcCodes.ILLEGAL_ADDRESS,
    ILLEGAL_VALUE: ExcCodes.ILLEGAL_VALUE,
    DEVICE_FAILURE: ExcCodes.DEVICE_FAILURE,
}
#: Names of the exception codes (Modbus application protocol v1.1b3, section 7), for the one-line error.
_EXC_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    6: "server device busy",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}
_HOLDING_FC = {3, 6, 16, 22, 23}
_INPUT_FC = {4}
FRAMINGS = ("tcp", "rtu")

# pymodbus logs connection failures itself; the link reports them once, in one line (CLI contract).
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


class ModbusAdapterError(Exception):
    """A failed Modbus exchange, in one line. ``exception_code``: the device's Modbus exception code, if it sent one."""

    def __init__(self, message: str, exception_code: int | None = None) -> None:
        super().__init__(message)
        self.exception_code = exception_code


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:200] or type(exc).__name__


# ---------------------------------------------------------------------------------------------- client
class RegisterClient:
    """A Modbus client for one unit. ``framing``: ``"tcp"`` (MBAP) or ``"rtu"``; ``serial_port`` set = RTU on a
    serial line (``host``/``port`` ignored) with ``baud`` and ``parity`` (``N``, ``E``, ``O``)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 502,
        *,
        framing: str = "tcp",
        unit: int = 1,
        timeout_s: float = 2.0,
        serial_port: str | None = None,
        baud: int = 19200,
        parity: str = "E",
    ) -> None:
        if framing not in FRAMINGS:
            raise ValueError(f"framing must be one of {FRAMINGS}")
        self.unit = int(unit)
        self.where = serial_port or f"{host}:{port}"
        framer = FramerType.RTU if framing == "rtu" else FramerType.SOCKET
        if serial_port is not None:
            self._client = ModbusSerialClient(
                serial_port,
                framer=FramerType.RTU,
                baudrate=int(baud),
                parity=parity,
                stopbits=1,
                bytesize=8,
                timeout=timeout_s,
                retries=0,
            )
        else:
            self._client = ModbusTcpClient(
                host,
                port=int(port),
                framer=framer,
                timeout=timeout_s,
                retries=0,
                reconnect_delay=0,
                reconnect_delay_max=0,
            )
        try:
            ok = self._client.connect()
        except (ModbusException, OSError) as exc:
            raise ModbusAdapterError(f"cannot connect to {self.where}: {_one_line(exc)}") from None
        if not ok:
            raise ModbusAdapterError(f"cannot connect to {self.where}")

    def _check(self, response: object, what: str) -> object:
        if response.isError():  # type: ignore[attr-defined]
            code = getattr(response, "exception_code", None)
            name = _EXC_NAMES.get(code, "unknown")
            raise ModbusAdapterError(
                f"{self.where}: {what} answered with Modbus exception {code} ({name}) by unit "
                f"{self.unit} (is that the sensor's unit id?)",
                exception_code=code,
            )
        return response

    def read(self, table: str, address: int, count: int) -> list[int]:
        """``count`` (<= 125) registers of ``table`` (``holding`` or ``input``) from ``address``."""
        fn = self._client.read_input_registers if table == "input" else self._client.read_holding_registers
        what = f"read of {count} {table} registers at {address}"
        try:
            rr = self._check(fn(address, count=count, device_id=self.unit), what)
        except (ModbusException, OSError) as exc:  # OSError: the peer reset the connection mid-exchange
            raise ModbusAdapterError(f"{self.where}: {what} failed ({_one_line(exc)})") from None
        regs = list(rr.registers)  # type: ignore[attr-defined]
        if len(regs) < count:
            raise ModbusAdapterError(f"{self.where}: {what} returned {len(regs)} registers")
        return regs[:count]

    def write(self, address: int, values: list[int]) -> None:
        """Write holding registers from ``address`` (function code 16)."""
        what = f"write of {len(values)} holding registers at {address}"
        try:
            self._check(self._client.write_registers(address, [int(v) for v in values], device_id=self.unit), what)
        except (ModbusException, OSError) as exc:  # OSError: the peer reset the connection mid-exchange
            raise ModbusAdapterError(f"{self.where}: {what} failed ({_one_line(exc)})") from None

    def close(self) -> None:
        self._client.close()


# ---------------------------------------------------------------------------------------------- server
class RegisterServer:
    """A Modbus server on ``host:port`` (``port=0``: any free port, see :attr:`port` after :meth:`start`) serving
    ``holding_size`` holding and ``input_size`` input registers of unit ``unit`` through the two callbacks."""

    def __init__(
        self,
        *,
        holding_size: int,
        input_size: int,
        on_read: Callable[[str, int, int], list[int]],
        on_write: Callable[[int, list[int]], None],
        framing: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 0,
        unit: int = 1,
    ) -> None:
        if framing not in FRAMINGS:
            raise ValueError(f"framing must be one of {FRAMINGS}")
        self.framing = framing
        self.host = host
        self.port = int(port)
        self.unit = int(unit)
        self._sizes = (int(holding_size), int(input_size))
        self._on_read, self._on_write = on_read, on_write
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if function_code in _HOLDING_FC:
            table = "holding"
        elif function_code in _INPUT_FC:
            table = "input"
        else:
            return ExcCodes.ILLEGAL_FUNCTION  # no coils or discrete inputs on this device
        try:
            if set_values is not None:
                self._on_write(address, [int(v) for v in set_values])
            else:
                values = self._on_read(table, address, count)
                offset = address - start_address
                current_registers[offset : offset + count] = [int(v) & 0xFFFF for v in values]
        except ModbusAdapterError as exc:
            return _EXC.get(exc.exception_code or DEVICE_FAILURE, ExcCodes.DEVICE_FAILURE)
        return None

    def _device(self) -> SimDevice:
        holding, inputs = self._sizes
        return SimDevice(
            id=self.unit,
            simdata=(
                [SimData(0, values=False, datatype=DataType.BITS)],
                [SimData(0, values=False, datatype=DataType.BITS)],
                [SimData(0, count=holding, values=0, datatype=DataType.REGISTERS)],
                [SimData(0, count=inputs, values=0, datatype=DataType.REGISTERS)],
            ),
            action=self._action,
        )

    async def _serve(self) -> None:
        try:
            framer = FramerType.RTU if self.framing == "rtu" else FramerType.SOCKET
            self._server = ModbusTcpServer(self._device(), framer=framer, address=(self.host, self.port))
            await self._server.serve_forever(background=True)
            sockets = getattr(self._server.transport, "sockets", None)
            if sockets:
                self.port = int(sockets[0].getsockname()[1])
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._started.set()
            return
        self._started.set()
        await self._server.serving

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        try:
            self._loop.run_until_complete(self._serve())
        finally:
            self._loop.close()

    def start(self, timeout_s: float = 5.0) -> RegisterServer:
        self._thread = threading.Thread(target=self._run, name=f"modbus-{self.framing}-server", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise ModbusAdapterError(f"Modbus server on {self.host}:{self.port} did not start")
        if self._error is not None:
            raise ModbusAdapterError(f"Modbus server on {self.host}:{self.port}: {_one_line(self._error)}")
        return self

    def stop(self) -> None:
        if self._loop is not None and self._server is not None and not self._loop.is_closed():
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(2.0)
            except (RuntimeError, TimeoutError, asyncio.CancelledError):
                pass
        if self._thread is not None:
            self._thread.join(2.0)
