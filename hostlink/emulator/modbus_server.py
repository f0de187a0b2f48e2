"""The emulated sensor's Modbus register server (docs/architecture.md: emulator/): a TCP server (MBAP, or RTU framing
over TCP) whose holding and input registers are served by two callbacks, ``on_read(table, address, count) ->
list[int]`` and ``on_write(address, values)``; raising :class:`~hostlink.links.modbus_adapter.ModbusAdapterError`
with an ``exception_code`` in a callback answers the request with that Modbus exception. It runs its own asyncio loop
on a daemon thread. Beside ``hostlink.links.modbus_adapter`` (the client), the only module that calls pymodbus.

pymodbus 3.16 facts this relies on (checked against its source): ``ModbusTcpServer`` takes a ``SimDevice`` whose async
``action`` sees every request before the datastore does (reads may fill ``current_registers``, writes happen after).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from hostlink.errors import one_line
from hostlink.links.modbus_adapter import (
    DEVICE_FAILURE,
    FRAMINGS,
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    ModbusAdapterError,
)

_EXC = {
    ILLEGAL_FUNCTION: ExcCodes.ILLEGAL_FUNCTION,
    ILLEGAL_ADDRESS: ExcCodes.ILLEGAL_ADDRESS,
    ILLEGAL_VALUE: ExcCodes.ILLEGAL_VALUE,
    DEVICE_FAILURE: ExcCodes.DEVICE_FAILURE,
}
#: Function codes that address holding registers (read, write single, write multiple, mask write, read/write) and
#: input registers (Modbus application protocol v1.1b3, section 6).
_HOLDING_FC = {3, 6, 16, 22, 23}
_INPUT_FC = {4}


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
            raise ModbusAdapterError(f"Modbus server on {self.host}:{self.port}: {one_line(self._error)}")
        return self

    def stop(self) -> None:
        if self._loop is not None and self._server is not None and not self._loop.is_closed():
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(2.0)
            except (RuntimeError, TimeoutError, asyncio.CancelledError):
                pass
        if self._thread is not None:
            self._thread.join(2.0)
