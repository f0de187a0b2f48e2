"""An in-process link to an :class:`~hostlink.emulator.sensor.EmulatedSensor`: every message is encoded to bytes and
decoded again on each side, but nothing touches a port. For tests of the host operations and the firmware, and for
measuring host-side decoding; not a user-selectable ``--link``.

``tamper(command_bytes) -> bytes | None`` lets a test corrupt (or drop, returning None) a command on its way.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from hostlink.emulator.sensor import EmulatedSensor
from hostlink.errors import LinkError
from hostlink.links.base import DEFAULT_TIMEOUT_S, MessageLink
from protocol.messages import DecodeError, Message, decode, encode


class LoopbackLink(MessageLink):
    max_chunk_bytes = 16

    def __init__(
        self,
        sensor: EmulatedSensor,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        tamper: Callable[[bytes], bytes | None] | None = None,
        max_chunk_bytes: int = 16,
    ) -> None:
        super().__init__(timeout_s)
        self.name = "loopback"
        self.sensor = sensor
        self.tamper = tamper
        self.max_chunk_bytes = max_chunk_bytes
        self._inbox: deque[bytes] = deque()
        self.closed = False

    def _send(self, msg: Message) -> None:
        if self.closed:
            raise LinkError("loopback: closed")
        data = encode(msg)
        if self.tamper is not None:
            data = self.tamper(data)
            if data is None:
                return
        self.stats.tx_bytes += len(data)
        try:
            command = decode(data)
        except DecodeError:
            return  # the sensor ignores what it cannot decode; the host times out
        self._inbox.append(encode(self.sensor.handle(command)))

    def _receive(self, timeout_s: float) -> Message | None:
        if not self._inbox and self.sensor.streaming:
            msg = self.sensor.next_stream_message()
            if msg is not None:
                self._inbox.append(encode(msg))

        if not self._inbox:
            return None
        data = self._inbox.popleft()
        self.stats.rx_bytes += len(data)
        self.stats.rx_messages += 1
        return decode(data)

    def close(self) -> None:
        self.closed = True
