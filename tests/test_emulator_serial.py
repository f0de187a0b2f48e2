"""The emulator process: replay streams exactly the file's rows once, losses on the line are counted from
sequence numbers, the serial line is never faster than its baud rate, and it stops cleanly on SIGTERM."""

import os
import signal
import time

import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.emulator.sensor import Pacer
from hostlink.files.session import read_session, write_session
from hostlink.links import open_link
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from protocol.framing import framed_size
from protocol.messages import CENTROID_LSB_PX, frame_message_bytes


@pytest.fixture(scope="module")
def replay_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "session.csv"
    sim = simulate(SimConfig(camera=seed004_camera(), frames=50, noise_px=0.01, seed=11, false_star_fraction=0.1))
    write_session(path, sim.session)
    return path


def test_replay_streams_exactly_the_rows_of_the_file(replay_file, tmp_path):
    source = read_session(replay_file)
    assert np.any(source.star_id == 0)  # false stars (no identity, no reference direction) are replayed too
    with running_emulator("serial", "--replay", str(replay_file)) as info:
        out = tmp_path / "out.csv"
        run = hostlink("stream", "--link", info["link"], "--frames", "1000", "--out", str(out))
        assert run.returncode == 0, run.stderr
        assert "stream ended after 50 frames" in run.stderr and "lost 0" in run.stderr
        got = read_session(out)
    assert len(got) == len(source)
    assert np.array_equal(got.frame, source.frame) and np.array_equal(got.star_id, source.star_id)
    assert list(got.t_utc) == list(source.t_utc)
    assert np.array_equal(got.mag, source.mag, equal_nan=True)
    # fixed point: each coordinate is the file's rounded to the nearest 2^-10 px step
    assert np.max(np.abs(got.x_px - source.x_px)) <= CENTROID_LSB_PX / 2
    assert np.max(np.abs(got.y_px - source.y_px)) <= CENTROID_LSB_PX / 2


def test_messages_lost_on_the_line_are_counted_from_sequence_numbers(replay_file, tmp_path):
    with running_emulator("serial", "--replay", str(replay_file), "--drop-every", "10") as info:
        run = hostlink("stream", "--link", info["link"], "--frames", "1000", "--out", str(tmp_path / "o.csv"))
    assert run.returncode == 0, run.stderr
    # frames 10, 20, 30, 40, 50 of the 50 are lost; the end-of-stream message after them reveals the last gap
    assert "45 frames" in run.stderr and "lost 5 message(s)" in run.stderr


def test_the_line_is_never_faster_than_the_baud_rate(replay_file):
    baud = 115_200
    with running_emulator("serial", "--replay", str(replay_file), "--baud", str(baud)) as info:
        with open_link(info["link"]) as link:
            link.set_streaming(True)
            frames = [link.recv_frame()]  # the clock starts at the first frame
            start = time.monotonic()
            while (f := link.recv_frame()) is not None:
                frames.append(f)
            elapsed = time.monotonic() - start
    assert len(frames) == 50
    wire_bytes = sum(framed_size(frame_message_bytes(f.n_stars)) for f in frames[1:])
    # the pacer may start up to its 5 ms FIFO credit early; everything else only makes the stream slower
    assert elapsed >= wire_bytes * 10 / baud - 0.006


def test_pacer_holds_the_line_rate_and_absorbs_sleep_jitter():
    now = [0.0]

    def sleep(dt):
        now[0] += dt + 1e-4  # every sleep overshoots by 100 us

    pacer = Pacer(1000.0, credit_s=0.005, clock=lambda: now[0], sleep=sleep)
    for _ in range(1000):
        pacer.wait(10)  # 10 ms per message at 1000 bit/s
    # 1000 messages = 10 s of line time; overshoot is absorbed by the credit, not accumulated (1000 x 0.1 ms)
    assert 9.99 <= now[0] <= 10.0 + 0.001


def test_emulator_stops_cleanly_on_sigterm():
    with running_emulator("serial", "--sim-frames", "20") as info:
        proc = info["process"]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0


def test_emulator_with_a_missing_replay_file_is_a_one_line_error(tmp_path):
    run = hostlink("emulate", "--transport", "serial", "--replay", str(tmp_path / "none.csv"))
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "no such file" in run.stderr
    assert run.stdout == ""


def test_estimates_read_over_the_link_equal_the_in_process_firmware_whatever_the_host_speed(replay_file):
    """The emulator process decides which exposures its estimator processes by the firmware's modelled budget, not
    by measured host time: every estimate read over a real pty (whose timing varies from run to run and with the
    machine's load) equals, bit for bit, the estimate of the same firmware fed the same file in process."""
    from hostlink.emulator.setup import build_sensor
    from hostlink.links.operations import stream_frames
    from protocol.messages import ReadEstimate, StreamControl

    with running_emulator("serial", "--replay", str(replay_file)) as info:
        with open_link(info["link"]) as link:
            result = stream_frames(link, None, poll_every_frames=7, keep_frames=False)
    polled = [p.estimate for p in result.polls if p.estimate is not None]
    assert len(polled) == 50 // 7 and result.frames_received == 50

    # the same firmware as the emulator's (HOSTLINK_FIRMWARE runs the suite against the C core)
    reference = build_sensor(replay=str(replay_file), firmware=os.environ.get("HOSTLINK_FIRMWARE") or "python")
    reference.handle(StreamControl(tag=1, enable=True))
    by_frame = {}
    while (msg := reference.next_stream_message()) is not None and hasattr(msg, "frame"):
        by_frame[msg.frame] = reference.handle(ReadEstimate(tag=2))
    assert reference.firmware.counters.estimator_skipped == 0  # 1 s frames: the default budget processes all
    for est in polled:
        ref = by_frame[est.last_frame]
        assert (est.n_updates, est.values, est.sigma) == (ref.n_updates, ref.values, ref.sigma)
