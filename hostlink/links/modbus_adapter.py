"""The host's Modbus client, the one place the host side calls pymodbus (pinned to one minor release in pyproject.toml):
a register client a few methods wide, so a pymodbus upgrade touches this file and the emulator's register server
(``hostlink.emulator.modbus_server``) alone.

* :class:`RegisterClient` -- Modbus TCP, RTU framing over TCP (an RS-485 gateway, or the emulator), or RTU on a
  serial port; ``read(table, address, count)``, ``write(address, values)``, ``close()``. Failures raise
  :class:`ModbusAdapterError` with one line (``exception_code`` set when the device answered with a Modbus exception).

pymodbus 3.16 facts this relies on (checked against its source): ``ModbusTcpClient`` accepts
``framer=FramerType.RTU`` (RTU over TCP); request methods take ``device_id=``; the sync clients read their answer
timeout from ``comm_params.timeout_connect`` at every exchange (so :meth:`RegisterClient.set_answer_timeout` can
change it between exchanges) and call their own ``recv`` for every read from the line (wrapped here to learn whether
any byte of an answer came, and to shorten the wait for the rest of a Modbus TCP answer begun, ``_ANSWER_REST_S``:
pymodbus frames by the MBAP length and would wait for a byte lost on the way until the whole answer wait ended);
``set_max_no_responses`` sets how many unanswered requests in a row make pymodbus close
the connection by itself (default 3: "No response received ... CLOSING CONNECTION"), which this client turns off
because the link decides when to reconnect (the limit is ``transaction.max_until_disconnect``, the running count
``transaction.count_until_disconnect``, reset to the limit only by an answer: both are set).
"""

from __future__ import annotations

import logging

from pymodbus import FramerType, ModbusException
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from hostlink.errors import one_line

#: Modbus exception codes (Modbus application protocol v1.1b3, section 7).
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
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
FRAMINGS = ("tcp", "rtu")
#: Unanswered requests in a row after which pymodbus would close the connection by itself: never (the link resets
#: the connection after every failed exchange itself, and a noisy line must not end the link).
_NEVER_CLOSE = 1 << 30
#: Longest wait for the rest of a Modbus TCP answer whose MBAP header has arrived and promises more bytes [s]: a device
#: writes its answer at once (one TCP segment on a LAN), so the rest follows within a few scheduler ticks of the host
#: (Linux: 1-4 ms) or never (a byte dropped on the way: the length field then promises a byte that will not come).
#: Without it pymodbus waits for that byte until the whole answer wait has passed, and on a noisy line (where failed
#: tries back the wait off to the device's longest response time) every damaged answer cost the longest wait.
_ANSWER_REST_S = 0.02
#: MBAP header bytes up to and including the length field (transaction id, protocol id, length: Modbus messaging on
#: TCP/IP implementation guide v1.0b, 3.1.3); the length counts the bytes after it.
_MBAP_LENGTH_END = 6

# pymodbus logs connection failures itself; the link reports them once, in one line (CLI contract).
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


class ModbusAdapterError(Exception):
    """A failed Modbus exchange, in one line. ``exception_code``: the device's Modbus exception code, if it sent one;
    ``answered``: bytes of an answer arrived (the device is there; the answer was cut short or garbled on the way)."""

    def __init__(self, message: str, exception_code: int | None = None, answered: bool = False) -> None:
        super().__init__(message)
        self.exception_code = exception_code
        self.answered = answered


def answer_cut_short(received: bytes) -> bool:
    """Whether Modbus TCP bytes received in one exchange end inside a frame: whole MBAP frames (a late answer to an
    earlier request, which pymodbus skips by its transaction id) followed by a header whose length field promises more
    bytes than came, or by bytes pymodbus cannot frame at all (a protocol id other than 0: it never skips them, so
    nothing after them is taken in this exchange). Modbus messaging on TCP/IP implementation guide v1.0b, 3.1.3."""
    at = 0
    while len(received) - at >= _MBAP_LENGTH_END:
        if received[at + 2 : at + 4] != b"\x00\x00":
            return True
        end = at + _MBAP_LENGTH_END + int.from_bytes(received[at + 4 : at + 6], "big")
        if end > len(received):
            return True
        at = end
    return at < len(received)


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
        self._client.set_max_no_responses(_NEVER_CLOSE)
        # set_max_no_responses sets the limit but not the running count (retries + 3 until the first answer): without
        # this, four unanswered requests before any answer still closed the connection with pymodbus's own message
        transaction = getattr(self._client, "transaction", None)
        if transaction is not None and hasattr(transaction, "count_until_disconnect"):
            transaction.count_until_disconnect = _NEVER_CLOSE
        self._timeout_s = float(timeout_s)  # the answer wait of the next exchanges
        self._mbap = serial_port is None and framing == "tcp"
        self._rx = bytearray()  # bytes received in the current exchange (the sync client's recv, wrapped)
        receive = self._client.recv

        def counted_recv(size: int | None) -> bytes:
            data = receive(size)
            self._rx += data
            if self._mbap:  # pymodbus reads the line's timeout at every recv: the rest of a begun answer waits less
                wait_s = min(self._timeout_s, _ANSWER_REST_S) if answer_cut_short(bytes(self._rx)) else self._timeout_s
                self._client.comm_params.timeout_connect = wait_s
            return data

        self._client.recv = counted_recv
        try:
            ok = self._client.connect()
        except (ModbusException, OSError) as exc:
            raise ModbusAdapterError(f"cannot connect to {self.where}: {one_line(exc)}") from None
        if not ok:
            raise ModbusAdapterError(f"cannot connect to {self.where}")

    def set_answer_timeout(self, timeout_s: float) -> None:
        """How long the next exchanges wait for their answer [s]."""
        self._timeout_s = float(timeout_s)
        self._client.comm_params.timeout_connect = self._timeout_s

    def _begin(self) -> None:
        """A new exchange: nothing received yet, the whole answer wait ahead."""
        self._rx = bytearray()
        self._client.comm_params.timeout_connect = self._timeout_s

    def _check(self, response: object, what: str) -> object:
        if response.isError():  # type: ignore[attr-defined]
            code = getattr(response, "exception_code", None)
            name = _EXC_NAMES.get(code, "unknown")
            raise ModbusAdapterError(
                f"{self.where}: {what} answered with Modbus exception {code} ({name}) by unit "
                f"{self.unit} (is that the sensor's unit id?)",
                exception_code=code,
                answered=True,
            )
        return response

    def read(self, table: str, address: int, count: int) -> list[int]:
        """``count`` (<= 125) registers of ``table`` (``holding`` or ``input``) from ``address``."""
        fn = self._client.read_input_registers if table == "input" else self._client.read_holding_registers
        what = f"read of {count} {table} registers at {address}"
        self._begin()
        try:
            rr = self._check(fn(address, count=count, device_id=self.unit), what)
        except (ModbusException, OSError) as exc:  # OSError: the peer reset the connection mid-exchange
            raise ModbusAdapterError(
                f"{self.where}: {what} failed ({one_line(exc)})", answered=len(self._rx) > 0
            ) from None
        finally:
            self._client.comm_params.timeout_connect = self._timeout_s  # (also the reconnect's timeout)
        regs = list(rr.registers)  # type: ignore[attr-defined]
        if len(regs) != count:  # a late answer to another read (RTU has no transaction id) or a garbled one
            raise ModbusAdapterError(f"{self.where}: {what} returned {len(regs)} registers", answered=True)
        return regs

    def write(self, address: int, values: list[int]) -> None:
        """Write holding registers from ``address`` (function code 16)."""
        what = f"write of {len(values)} holding registers at {address}"
        self._begin()
        try:
            rr = self._check(self._client.write_registers(address, [int(v) for v in values], device_id=self.unit), what)
        except (ModbusException, OSError) as exc:  # OSError: the peer reset the connection mid-exchange
            raise ModbusAdapterError(
                f"{self.where}: {what} failed ({one_line(exc)})", answered=len(self._rx) > 0
            ) from None
        finally:
            self._client.comm_params.timeout_connect = self._timeout_s
        echo = (getattr(rr, "address", address), getattr(rr, "count", len(values)))
        if echo != (address, len(values)):  # the answer echoes address and count: a late answer to another write
            raise ModbusAdapterError(f"{self.where}: {what} answered for {echo[1]} registers at {echo[0]}")

    def reset(self) -> None:
        """Drop the connection and open it again (after a failed exchange: bytes of a late or partial answer must
        not be taken for the next one). A failure to reconnect is left to the next exchange to report."""
        self._client.close()
        try:
            self._client.connect()
        except (ModbusException, OSError):
            pass

    def close(self) -> None:
        self._client.close()
