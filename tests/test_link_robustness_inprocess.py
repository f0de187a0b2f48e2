"""Link-layer robustness without a subprocess: a Modbus release that fails, oversized serial frames, can-isotp's
warnings, reply tags of a fresh link."""

import numpy as np
import pytest
from register_fakes import ImageRegisterClient

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.modbus_endpoint import RegisterSensor
from hostlink.emulator.sensor import EmulatedSensor, SourceFrame
from hostlink.errors import LinkError
from hostlink.links.modbus_adapter import ModbusAdapterError
from hostlink.links.modbus_link import ModbusLink
from onboard import banks
from onboard.firmware import Firmware
from onboard.params import CameraParams
from protocol import modbus_map as mm
from protocol.framing import FrameSplitter, encode_frame
from protocol.messages import CentroidFrame

NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)


def _source(n_frames: int):
    for k in range(n_frames):
        f = CentroidFrame(
            frame=k,
            t_us=1_700_000_000_000_000 + 100_000 * k,
            star_id=np.array([7, 9], np.uint32),
            x_px=np.array([10.0 + k, 20.0]),
            y_px=np.array([30.0, 40.0 + k]),
            mag=np.array([5.0, 6.0]),
        )
        yield SourceFrame(frame=f, r_ref=None)


def _sensor(n_frames: int = 10) -> EmulatedSensor:
    return EmulatedSensor(Firmware(banks.factory_store(NOMINAL), None), _source(n_frames))


class _FlakyRegisterClient(ImageRegisterClient):
    """A RegisterClient talking straight to the emulator's register image; ``fail_writes_at`` makes the write to
    that address fail once (the request reached the sensor or not: ``applied``)."""

    def __init__(self, image: RegisterSensor) -> None:
        super().__init__(image)
        self.fail_writes_at: int | None = None
        self.applied = False

    def write(self, address: int, values: list[int]) -> None:
        if address == self.fail_writes_at:
            self.fail_writes_at = None
            if self.applied:
                self.image.on_write(address, values)
            raise ModbusAdapterError("127.0.0.1:1: write timed out")
        self.image.on_write(address, values)


@pytest.mark.parametrize("applied", [False, True])
def test_modbus_failed_window_release_is_made_again_and_nothing_is_counted_lost(applied):
    client = _FlakyRegisterClient(RegisterSensor(_sensor()))
    link = ModbusLink(client, "modbus-tcp:fake:1", timeout_s=0.5)
    link.set_streaming(True)
    assert link.recv_frame().frame == 0
    client.fail_writes_at, client.applied = mm.load_map()["stream_ack_seq"].address, applied
    # the release of frame 1 fails on the way (whether or not it reached the sensor) and is written again: releasing
    # a window twice is releasing it once, so frame 2 follows and nothing is lost (never 2**32 - 1 messages)
    assert link.recv_frame().frame == 1 and link.stats.corrupt_frames == 1
    assert (link.recv_frame().frame, link.stats.lost_messages) == (2, 0)


def test_modbus_link_that_is_gone_ends_with_one_link_error_after_its_timeout():
    client = _FlakyRegisterClient(RegisterSensor(_sensor()))
    link = ModbusLink(client, "modbus-tcp:fake:1", timeout_s=0.3)
    link.set_streaming(True)

    def gone(*_args):
        raise ModbusAdapterError("127.0.0.1:1: connection refused")

    client.read = client.write = gone
    with pytest.raises(LinkError, match="connection refused"):
        link.recv_frame(0.3)
    assert link.stats.corrupt_frames > 0  # it tried again until the deadline


def test_frame_splitter_discards_an_oversized_frame_even_when_its_delimiter_came_in_the_same_read():
    splitter = FrameSplitter(max_frame_bytes=64)
    good = encode_frame(3, b"\x01hello")
    out = splitter.feed(b"\x55" * 200 + b"\x00" + good)
    assert out == [good[:-1]]
    assert splitter.discarded_bytes == 200
    # a tail longer than the limit is not kept waiting for its delimiter either
    assert splitter.feed(good + b"\x66" * 100) == [good[:-1]] and splitter.discarded_bytes == 300


def test_can_isotp_protocol_warnings_do_not_reach_stderr(caplog):
    import can

    from hostlink.links.can_link import IsoTpChannel
    from protocol import can_frames as cf

    ch = IsoTpChannel(lambda msg: None, cf.ISOTP_HOST_TO_SENSOR_ID, cf.ISOTP_SENSOR_TO_HOST_ID)
    # a flow control frame while nothing is being sent (what a second host on the bus causes)
    ch.feed(can.Message(arbitration_id=cf.ISOTP_SENSOR_TO_HOST_ID, data=bytes([0x30, 0, 0]), is_extended_id=False))
    ch.poll()
    # without a handler Python prints any WARNING record on stderr, a second line after the CLI's one-line error
    assert [r.getMessage() for r in caplog.records if r.name.startswith("isotp")] == []
    assert ch.errors == 1  # counted by the link instead


def test_fresh_links_do_not_all_start_at_the_same_reply_tag():
    # a stale reply left on a port by an earlier process must not match a new link's first command
    first_tags = {next(LoopbackLink(_sensor(0))._tags) for _ in range(20)}
    assert len(first_tags) > 1


def test_modbus_connection_reset_mid_exchange_is_an_adapter_error_not_an_internal_error():
    from hostlink.links.modbus_adapter import RegisterClient

    class _ResetClient:
        class comm_params:  # noqa: N801 - pymodbus's attribute: the answer wait, set at every exchange
            timeout_connect = 2.0

        def read_input_registers(self, *a, **k):
            raise ConnectionResetError(104, "Connection reset by peer")

        write_registers = read_input_registers

    client = object.__new__(RegisterClient)  # no socket: the pymodbus client is replaced by one whose peer died
    client.unit, client.where, client._client = 1, "127.0.0.1:1", _ResetClient()
    client._timeout_s = 2.0
    with pytest.raises(ModbusAdapterError, match="reset by peer"):
        client.read("input", 0, 4)
    with pytest.raises(ModbusAdapterError, match="reset by peer"):
        client.write(0, [1])


def test_a_stream_that_starts_the_moment_the_sensor_acknowledges_loses_no_frame():
    """The sensor may put the first frame on the bus before the host has read the ACK of STREAM_CONTROL (the CAN
    link's reader thread assembles it meanwhile): restarting loss counting after the ACK would cut that frame in
    half. Modelled without threads: sending the command already feeds frame 0 up to its FRAME_END."""
    from hostlink.links.base import MessageLink
    from hostlink.links.can_link import StreamAssembler
    from hostlink.links.operations import stream_frames
    from protocol import can_frames as cf
    from protocol.messages import Ack, EndOfStream, StreamControl

    encoder = cf.StreamEncoder()
    frames = [sf.frame for sf in _source(3)]
    can_frames = [cf_ for f in frames for cf_ in encoder.encode(f)]
    can_frames.append((cf.END_OF_STREAM.frame_id, cf.encode_end_of_stream(3, 2)))

    class _EagerSensorLink(MessageLink):
        name = "eager"

        def __init__(self) -> None:
            super().__init__(timeout_s=1.0)
            self.assembler = StreamAssembler()
            self.inbox: list = []
            self.pending: list[tuple[int, bytes]] = []

        def _send(self, msg) -> None:
            if isinstance(msg, StreamControl) and msg.enable:
                self.inbox.append(Ack(tag=msg.tag, command=int(StreamControl.TYPE)))
                self.pending = list(can_frames)
                while self.pending[0][0] != cf.FRAME_END.frame_id:  # frame 0 assembled before the ACK is read
                    self.assembler.feed(*self.pending.pop(0))
            elif isinstance(msg, StreamControl):
                self.inbox.append(Ack(tag=msg.tag, command=int(StreamControl.TYPE)))

        def _receive(self, timeout_s: float):
            while not self.inbox and self.pending:
                out = self.assembler.feed(*self.pending.pop(0))
                if out is not None:
                    self.inbox.append(out)
            self.stats.corrupt_frames = self.assembler.corrupt
            self.stats.lost_messages = self.assembler.lost
            return self.inbox.pop(0) if self.inbox else None

        def _reset_loss_counting(self) -> None:
            self.assembler.forget_sequence()

        def recv_frame(self, timeout_s=None):
            while not self._stream:
                msg = self._receive(0.0)
                if msg is None:
                    return None
                self._stream.append(msg)
            msg = self._stream.popleft()
            return None if isinstance(msg, EndOfStream) else msg

        def close(self) -> None:
            pass

    result = stream_frames(_EagerSensorLink(), None)
    assert [f.frame for f in result.frames] == [0, 1, 2]
    assert (result.lost_messages, result.corrupt_frames) == (0, 0)


def _drop_estimate_reads_while(state: dict):
    """A tamper hook: READ_ESTIMATE commands (every resend too) vanish on the line while ``state["drop"]``."""
    from protocol.messages import MsgType, decode

    def tamper(data: bytes) -> bytes | None:
        return None if state["drop"] and decode(data).TYPE == MsgType.READ_ESTIMATE else data

    return tamper


@pytest.mark.parametrize("allowed, completes", [(2, True), (1, False)])
def test_a_stream_goes_on_through_the_allowed_run_of_unanswered_polls(allowed, completes):
    """Polls after frames 10 and 15 get no reply (their commands are lost, whatever the host's speed): with 2 misses
    allowed the stream completes and reports them as unanswered; with 1 the second miss ends it with the LinkError."""
    from hostlink.links.operations import StreamResult, stream_frames

    state = {"drop": False}
    link = LoopbackLink(_sensor(40), timeout_s=0.05, tamper=_drop_estimate_reads_while(state))

    def on_frame(_frame) -> None:
        state["drop"] = 9 <= result.frames_received < 19  # frames_received counts up to the frame just in hand

    result = StreamResult()
    if completes:
        stream_frames(link, 30, result=result, on_frame=on_frame, poll_every_frames=5, missed_polls_allowed=allowed)
        assert [p.answered for p in result.polls] == [True, False, False, True, True, True]
        assert result.frames_received == 30 and not result.polls[1].estimate
        assert "no reply to READ_ESTIMATE" in result.polls[1].reason
    else:
        with pytest.raises(LinkError, match="no reply to READ_ESTIMATE"):
            stream_frames(link, 30, result=result, on_frame=on_frame, poll_every_frames=5, missed_polls_allowed=allowed)
        assert [p.answered for p in result.polls] == [True, False] and result.frames_received == 15
