"""Link integrity through the fault-injecting relay (issue 15): with bit errors (1e-4 per bit) and byte drops (1 %)
on the sensor -> host line, every transport delivers no corrupt centroid, reports exactly the frames it lost, and
completes the stream; a line that is cut for good ends with one line and exit code 3.

Short runs (the sensor streams 200 frames on serial and CAN, 15 on each Modbus framing: every lost Modbus answer
costs a response timeout); the 2,000-frame acceptance run is ``python scripts/link_faults.py``.
"""

import os
import socket
import time

import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.emulator.fault_relay import FaultModel, TcpRelay, relay_link
from hostlink.emulator.fault_run import stream_through_faults
from hostlink.files.session import write_session
from hostlink.links import open_link
from hostlink.links.operations import stream_frames
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate


def test_the_fault_model_drops_and_flips_at_the_rates_asked():
    model = FaultModel(ber=1e-3, drop=0.02, seed=3)
    data = bytes(200_000)
    out = model.apply(data)
    assert model.bytes_in == len(data) and len(out) == len(data) - model.bytes_dropped
    # binomial counts: 4000 expected drops and 1568 expected flips (of 196000 x 8 bits); 5 sigma is 6 % and 13 %
    assert model.bytes_dropped == pytest.approx(0.02 * len(data), rel=0.06)
    assert model.bits_flipped == pytest.approx(1e-3 * 8 * len(out), rel=0.13)
    assert sum(bin(b).count("1") for b in out) == model.bits_flipped  # zeros in: every 1 bit is a flip


def test_the_fault_model_is_reproducible_however_the_stream_is_cut_and_cuts_after_the_bytes_asked():
    a, b = FaultModel(1e-2, 0.1, seed=7), FaultModel(1e-2, 0.1, seed=7)
    data = np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes()
    assert a.apply(data) == b.apply(data[:1234]) + b.apply(data[1234:])
    cut = FaultModel(cut_after_bytes=100)
    assert cut.apply(bytes(60)) == bytes(60) and not cut.cut
    assert cut.apply(bytes(60)) == bytes(40) and cut.cut
    with pytest.raises(ValueError):
        FaultModel(ber=2.0)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("transport", "rtu", "frames"),
    [("serial", False, 200), ("can", False, 200), ("modbus", False, 15), ("modbus", True, 15)],
    ids=["serial", "can", "modbus-tcp", "modbus-rtu"],
)
def test_a_noisy_line_delivers_no_corrupt_centroid_and_counts_its_loss_exactly(transport, rtu, frames):
    r = stream_through_faults(transport, frames, ber=1e-4, drop=0.01, seed=5, rtu=rtu)
    assert r.down["bytes_dropped"] > 0 and r.down["bits_flipped"] > 0  # the line really was noisy
    assert r.corrupt_detected > 0  # and the link saw it
    assert r.corrupt_accepted == 0
    assert r.reported_loss == r.true_loss  # counted from frame 0: frames lost before the first received included
    # the stream went on to the end (on CAN at 1 % byte drops 0.01 % of the frames arrive whole: one may be all)
    assert r.frames_spanned >= frames and r.frames_received >= 1


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="counts open file descriptors in Linux /proc")
def test_the_tcp_relay_closes_each_connection_it_relayed():
    """A Modbus host reconnects after every few failed exchanges: thousands of connections in a 2,000-frame run. The
    relay must close both sockets of each ended connection (it once kept them open until the process ran out of file
    descriptors, and then closed every new connection at once)."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(5.0)
    relay = TcpRelay(server.getsockname(), FaultModel(), FaultModel())
    open_fds = lambda: len(os.listdir("/proc/self/fd"))  # noqa: E731
    try:
        before = open_fds()
        for _ in range(200):
            host = socket.create_connection(("127.0.0.1", relay.port), timeout=5.0)
            sensor, _ = server.accept()  # the relay's upstream connection
            host.sendall(b"x")
            assert sensor.recv(1) == b"x"
            host.close()
            sensor.close()
        deadline = time.monotonic() + 30.0  # the relay's pumps notice the ends within their poll period
        while open_fds() > before + 4 and time.monotonic() < deadline:
            time.sleep(0.05)  # polling an observable count with a deadline, not a synchronisation by sleep
        assert open_fds() <= before + 4  # at most the last connection's pair still closing
    finally:
        relay.close()
        server.close()


@pytest.mark.slow
def test_faults_on_the_requests_too_still_deliver_no_corrupt_centroid_on_modbus():
    """Both directions noisy: on Modbus the host -> sensor line carries every read request (several per frame), so a
    garbled or truncated request must be answered by nothing the host would take for a snapshot."""
    r = stream_through_faults("modbus", 15, ber=1e-4, drop=0.01, seed=5, both_directions=True)
    assert r.up["bytes_dropped"] > 0  # requests were hit
    assert r.corrupt_accepted == 0 and r.reported_loss == r.true_loss and r.frames_spanned >= 15


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_a_line_cut_for_good_is_one_line_and_exit_3(transport, tmp_path):
    with running_emulator(transport, "--sim-frames", "20", "--no-estimator") as info:
        link, relay = relay_link(info["link"], FaultModel(cut_after_bytes=20_000, seed=1))
        try:
            run = hostlink(
                "stream",
                "--link",
                link,
                "--frames",
                "100000",
                "--quiet",
                "--timeout",
                "2",
                "--out",
                str(tmp_path / "s.csv"),
            )
        finally:
            relay.close()
    assert run.returncode == 3, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr, run.stderr


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_replay_through_a_noisy_line_ends_even_when_its_end_of_stream_is_lost(transport, tmp_path):
    """The sensor repeats END_OF_STREAM while the stream is on: losing copies of it does not leave the host waiting."""
    path = tmp_path / "session.csv"
    write_session(path, simulate(SimConfig(camera=seed004_camera(), frames=30, noise_px=0.01, seed=2)).session)
    with running_emulator(transport, "--replay", str(path), "--no-estimator") as info:
        link, relay = relay_link(info["link"], FaultModel(ber=1e-4, drop=0.01, seed=9))
        try:
            with open_link(link, timeout_s=5.0) as sensor:
                result = stream_frames(sensor, None, frame_timeout_s=20.0)
        finally:
            relay.close()
    assert result.ended and result.frames_received < 30  # the line lost frames, yet the stream ended
