"""Serial endpoint of the emulated sensor: a pseudo-terminal, framed exactly like a UART sensor (``protocol.framing``),
paced to the baud rate (10 bits per byte: start, 8 data, stop).

The host opens the pty's slave side (``serial:/dev/pts/N@BAUD``) with pyserial like any port. The emulator keeps a
handle on the slave too, so hosts may come and go (each command opens and closes the port) without the master side
seeing a hang-up. One loop, one thread: read and answer commands, then, while streaming, send the next frame when
the line is free.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable

from hostlink.emulator.sensor import EmulatedSensor, EndpointOptions, Pacer
from protocol.framing import FrameSplitter, FramingError, decode_frame, encode_frame
from protocol.messages import DecodeError, EndOfStream, Message, Nak, NakCode, decode, encode, is_command

BITS_PER_BYTE = 10
#: After its source ended, the sensor repeats END_OF_STREAM this often while the stream is on [s] (a host that lost
#: it on a noisy line still learns that the stream ended; each copy is a message of its own, with its own sequence
#: number).
END_REPEAT_S = 0.25
#: How long the loop waits for a command when it has nothing to send [s] (also the stop latency).
_IDLE_WAIT_S = 0.05


class _PtyLine:
    """The sensor's side of the line: framing, sequence numbers, pacing, blocking writes that honour ``stop``."""

    def __init__(self, master_fd: int, baud: int, stop: threading.Event, drop_every: int) -> None:
        self.fd = master_fd
        self.stop = stop
        self.pacer = Pacer(baud)  # baud = bits per second on the line; a byte takes BITS_PER_BYTE of them
        self.splitter = FrameSplitter()
        self.tx_seq = 0  # replies
        self.stream_seq = 0  # stream messages: their own sequence, so the host counts lost frames, not lost replies
        self.drop_every = drop_every
        self.stream_count = 0

    def send(self, msg: Message, stream: bool = False) -> None:
        if stream:
            data = encode_frame(self.stream_seq, encode(msg))
            self.stream_seq = (self.stream_seq + 1) & 0xFFFF
        else:
            data = encode_frame(self.tx_seq, encode(msg))
            self.tx_seq = (self.tx_seq + 1) & 0xFFFF
        if stream:
            self.stream_count += 1
            if self.drop_every and self.stream_count % self.drop_every == 0:
                return  # test hook: the frame is lost on the line (its sequence number is skipped)
        self.pacer.wait(BITS_PER_BYTE * len(data))
        view = memoryview(data)
        while view and not self.stop.is_set():
            _, writable, _ = select.select([], [self.fd], [], _IDLE_WAIT_S)
            if writable:
                view = view[os.write(self.fd, view) :]

    def commands(self, wait_s: float) -> list[Message]:
        readable, _, _ = select.select([self.fd], [], [], wait_s)
        if not readable:
            return []
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return []
        out = []
        for raw in self.splitter.feed(data):
            try:
                out.append(decode(decode_frame(raw).payload))
            except (FramingError, DecodeError):
                continue  # a corrupt command is never answered: the host times out and may retry
        return out


def serve(
    sensor: EmulatedSensor, options: EndpointOptions, ready: Callable[[dict], None], stop: threading.Event
) -> None:
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        os.set_blocking(master, False)
        line = _PtyLine(master, options.baud, stop, options.drop_every)
        ready({"link": f"serial:{os.ttyname(slave)}@{options.baud}", "transport": "serial", "baud": options.baud})
        end: EndOfStream | None = None  # the last END_OF_STREAM sent, repeated while the stream stays on
        next_end_s = 0.0
        while not stop.is_set():
            for cmd in line.commands(0.0 if sensor.streaming else _IDLE_WAIT_S):
                if is_command(cmd):
                    started = sensor.streams_started
                    reply = sensor.handle(cmd)
                    if sensor.streams_started != started:
                        line.stream_seq = 0  # a new stream: its messages are numbered from 0
                    line.send(reply)
                else:
                    line.send(
                        Nak(
                            tag=getattr(cmd, "tag", 0),
                            command=int(cmd.TYPE),
                            code=NakCode.UNKNOWN_COMMAND,
                            text=f"{cmd.TYPE.name} is not a command",
                        )
                    )
            # the next exposure (the firmware estimates it while the line is still busy with the previous one)
            msg = sensor.next_stream_message()
            if msg is not None:
                line.send(msg, stream=True)
                end = msg if isinstance(msg, EndOfStream) else None
                next_end_s = time.monotonic() + END_REPEAT_S
            elif sensor.streaming:
                if end is not None and time.monotonic() >= next_end_s:
                    line.send(end, stream=True)  # repeated: a lost END_OF_STREAM must not leave the host waiting
                    next_end_s += END_REPEAT_S
                stop.wait(_IDLE_WAIT_S)  # source exhausted: nothing to send until a command arrives
    finally:
        os.close(master)
        os.close(slave)
