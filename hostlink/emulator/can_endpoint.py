"""CAN endpoint of the emulated sensor: an SLCAN hub on 127.0.0.1 (the emulated bus, paced to its bit rate) with the
sensor as one node on it.

``hostlink emulate --transport can [--bitrate N]`` prints ``{"link": "can:slcan:socket://127.0.0.1:PORT@N", ...}``;
the host opens it with python-can's ``slcan`` interface like a USB SLCAN adapter. The sensor node speaks the frames
of ``protocol.can_frames``: COMMAND / STAGE_FLOAT in, ACK out, ISO-TP both ways for long messages, and the stream as
TIME_BASE + FRAME_HEADER + one STAR per star. Pacing is the bus's: a frame leaves only when the hub has bus time for
it (``hostlink.emulator.slcan_hub``), so the stream runs at the bit rate, never faster.

Two threads: the command reader (decode, ``sensor.handle``, reply) and the streamer. A command and its reply are
atomic with respect to the stream (one lock), so the ACK of STREAM_CONTROL precedes the first frame of the stream it
started. Everything the sensor decides, the firmware decides; this module only carries it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can

from hostlink.emulator.sensor import EmulatedSensor, EndpointOptions
from hostlink.emulator.slcan_hub import SLCAN_BITRATES, HubBus, SlcanHub
from hostlink.errors import UserError
from hostlink.links.can_link import IsoTpChannel
from protocol import can_frames as cf
from protocol.messages import (
    CentroidFrame,
    Commit,
    DecodeError,
    EncodeError,
    EndOfStream,
    Message,
    Nak,
    NakCode,
    StreamControl,
    decode,
    encode,
    is_command,
)

#: After its source ended, the sensor repeats END_OF_STREAM this often while the stream is on [s].
END_REPEAT_S = 0.25
#: Longest the sensor waits for bus time for one frame before it gives up on the stream [s].
_SEND_TIMEOUT_S = 2.0
_IDLE_WAIT_S = 0.02
#: how long the stream loop steps aside while a command waits for the lock [s]
_COMMAND_YIELD_S = 0.0005
#: The sensor's software transmit ring [CAN frames]: the stream keeps the bus busy while the firmware computes the
#: next exposure (256 frames = 69 ms of bus time at 500 kbit/s; 2 KiB of RAM).
SENSOR_TX_RING_FRAMES = 256


class SensorNode:
    """The emulated sensor's CAN controller and its two threads."""

    def __init__(self, sensor: EmulatedSensor, bus: can.BusABC, stop: threading.Event, drop_every: int = 0) -> None:
        self.sensor = sensor
        self.bus = bus
        self.stop = stop
        self.drop_every = int(drop_every)
        self.stream_count = 0
        self.stream_encoder = cf.StreamEncoder()
        self._end: EndOfStream | None = None  # the last END_OF_STREAM sent, repeated while the stream stays on
        self._next_end_s = 0.0
        self.last_frame = 0  # frame counter of the last frame produced (sent or dropped)
        self.undecodable = 0
        self._order = threading.Lock()  # a command + its reply vs. one stream message
        self._command_waiting = threading.Event()
        self._isotp = IsoTpChannel(self._send_frame, cf.ISOTP_SENSOR_TO_HOST_ID, cf.ISOTP_HOST_TO_SENSOR_ID)
        self._commit_bind: bytes | None = None  # payload of the last COMMIT_BIND frame, until the next command frame
        self._threads = [
            threading.Thread(target=self._command_loop, name="can-sensor-commands", daemon=True),
            threading.Thread(target=self._stream_loop, name="can-sensor-stream", daemon=True),
        ]

    def start(self) -> SensorNode:
        for t in self._threads:
            t.start()
        return self

    def join(self, timeout_s: float = 2.0) -> None:
        for t in self._threads:
            t.join(timeout_s)

    def _send_frame(self, msg: can.Message) -> None:
        self.bus.send(msg, timeout=_SEND_TIMEOUT_S)

    def _send_data(self, frame_id: int, data: bytes) -> None:
        self._send_frame(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    # ---------------------------------------------------------------------------------------- commands
    def _command_loop(self) -> None:
        while not self.stop.is_set():
            try:
                msg = self.bus.recv(0.001 if self._isotp.busy else _IDLE_WAIT_S)
            except can.CanError:
                return
            if msg is not None and not (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id):
                fid = msg.arbitration_id
                if fid == cf.ISOTP_HOST_TO_SENSOR_ID:
                    self._isotp.feed(msg)
                elif fid == cf.COMMIT_BIND.frame_id:
                    self._commit_bind = bytes(msg.data)  # joins the COMMAND COMMIT frame that follows
                elif fid in (cf.COMMAND.frame_id, cf.STAGE_FLOAT.frame_id):
                    bind, self._commit_bind = self._commit_bind, None
                    try:
                        cmd = cf.decode_single(fid, bytes(msg.data))
                        self._answer(cf.bind_commit(cmd, bind) if isinstance(cmd, Commit) else cmd)
                    except cf.CanDecodeError:
                        self.undecodable += 1  # a corrupt command is never answered: the host times out
            for payload in self._isotp.poll():
                try:
                    self._answer(decode(payload))
                except DecodeError:
                    self.undecodable += 1

    def _answer(self, cmd: Message) -> None:
        # Tell the stream loop a command is waiting: a thread that releases and re-takes a lock at once can starve
        # the other (Python locks are not fair), which held a StreamControl(stop) back for hundreds of frames.
        self._command_waiting.set()
        try:
            self._answer_locked(cmd)
        finally:
            self._command_waiting.clear()

    def _answer_locked(self, cmd: Message) -> None:
        with self._order:
            if is_command(cmd):
                reply = self.sensor.handle(cmd)
                if isinstance(cmd, StreamControl) and cmd.enable:
                    self.stream_encoder.restart()  # a (re)started stream begins with a TIME_BASE
                    self._end = None
            else:
                reply = Nak(
                    tag=getattr(cmd, "tag", 0),
                    command=int(cmd.TYPE),
                    code=NakCode.UNKNOWN_COMMAND,
                    text=f"{cmd.TYPE.name} is not a command",
                )
            try:
                if cf.is_single_frame(reply):
                    self._send_data(*cf.encode_single(reply))
                else:
                    self._isotp.send(encode(reply))
            except can.CanError:
                pass  # bus gone: the host times out

    # ------------------------------------------------------------------------------------------ stream
    def _stream_loop(self) -> None:
        while not self.stop.is_set():
            if self._command_waiting.is_set():
                self.stop.wait(_COMMAND_YIELD_S)  # commands first: at most one frame of delay for a command
                continue
            with self._order:
                msg = self.sensor.next_stream_message()
                if msg is not None:
                    self.stream_count += 1
                    if isinstance(msg, CentroidFrame):
                        self.last_frame = msg.frame
                    if self.drop_every and self.stream_count % self.drop_every == 0:
                        continue  # test hook: this message is lost on the bus
                    try:
                        self._send_stream_message(msg)
                    except can.CanError:
                        return
                    except EncodeError:
                        continue  # a centroid the CAN layout cannot carry: the frame is dropped (counted as lost)
            if msg is None:
                if self._end is not None and self.sensor.streaming and time.monotonic() >= self._next_end_s:
                    self._next_end_s = time.monotonic() + END_REPEAT_S
                    try:  # repeated: a lost END_OF_STREAM must not leave the host waiting
                        self._send_stream_message(self._end)
                    except can.CanError:
                        return
                self.stop.wait(_IDLE_WAIT_S)
            elif isinstance(msg, EndOfStream):
                self._end, self._next_end_s = msg, time.monotonic() + END_REPEAT_S

    def _send_stream_message(self, msg: CentroidFrame | EndOfStream) -> None:
        if isinstance(msg, EndOfStream):
            self._send_data(cf.END_OF_STREAM.frame_id, cf.encode_end_of_stream(msg.frames_sent, self.last_frame))
            return
        for frame_id, data in self.stream_encoder.encode(msg):  # EncodeError before anything is sent
            self._send_data(frame_id, data)


def check_bitrate(bitrate: int) -> int:
    if int(bitrate) not in SLCAN_BITRATES.values():
        allowed = ", ".join(str(v) for v in sorted(SLCAN_BITRATES.values()))
        raise UserError(f"--bitrate {bitrate}: not a CAN bit rate an SLCAN adapter offers ({allowed})")
    return int(bitrate)


def serve(
    sensor: EmulatedSensor, options: EndpointOptions, ready: Callable[[dict], None], stop: threading.Event
) -> None:
    bitrate = check_bitrate(options.bitrate)
    hub = SlcanHub(bitrate, host=options.host, port=options.port).start()
    bus: HubBus = hub.attach("sensor", tx_queue_frames=SENSOR_TX_RING_FRAMES)
    node = SensorNode(sensor, bus, stop, options.drop_every).start()
    try:
        ready(
            {
                "link": f"can:slcan:{hub.url}@{bitrate}",
                "transport": "can",
                "bitrate": bitrate,
                "port": hub.port,
                "bits_per_frame": cf.frame_bits_worst_case(cf.CAN_PAYLOAD_BYTES, False),
            }
        )
        stop.wait()
    finally:
        stop.set()
        node.join()
        bus.shutdown()
        hub.stop()
