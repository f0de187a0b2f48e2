"""The bench's drift phase begins at the same exposure however many the sensor took while the host stopped the
calibration stream (issue 27: the CAN figure varied with host timing), in process and without timing: the emulated
sensor's phase starts (``hostlink emulate --phase-start``) and the bench replay's layout."""

import numpy as np
import pytest
from stream_frames import NOMINAL, one_star_frame

from hostlink.emulator.sensor import EmulatedSensor, SourceFrame
from hostlink.mission.config import BenchConfig, drift_first_frame
from hostlink.mission.run import concatenate_sessions, simulate_phases
from hostlink.mission.summary import drift_frame_index, replay_truth_attitudes, truth_attitudes
from onboard import banks
from onboard.firmware import Firmware
from protocol import messages as m

PHASE_START = 30  # the second phase's first frame counter in a 60-frame replay


def _frame(k: int) -> m.CentroidFrame:
    return one_star_frame(k, period_us=1_000_000)  # one exposure a second, as the bench's replay


class _CountingFirmware(Firmware):
    """The Python firmware, recording the frame counter of every exposure it processes (what its estimator sees)."""

    def __init__(self) -> None:
        super().__init__(banks.factory_store(NOMINAL), None)
        self.processed: list[int] = []

    def process_frame(self, frame, r_ref=None):
        self.processed.append(int(frame.frame))
        return super().process_frame(frame, r_ref)


def _second_stream(in_flight: int, phase_starts: tuple[int, ...]) -> tuple[int, list[int], list[int]]:
    """First stream: 20 frames received + ``in_flight`` more the sensor took before the stop reached it; then a new
    stream of 10 frames. Returns (the new stream's ACK value, its frame counters, the exposures processed)."""
    firmware = _CountingFirmware()
    source = (SourceFrame(frame=_frame(k), r_ref=None) for k in range(60))
    sensor = EmulatedSensor(firmware, source, phase_starts)
    sensor.handle(m.StreamControl(tag=1, enable=True))
    for _ in range(20 + in_flight):
        sensor.next_stream_message()
    sensor.handle(m.StreamControl(tag=2, enable=False))
    ack = sensor.handle(m.StreamControl(tag=3, enable=True))
    second = [sensor.next_stream_message().frame for _ in range(10)]
    return ack.value, second, firmware.processed


@pytest.mark.parametrize("in_flight", [0, 1, 7])
def test_a_restarted_stream_begins_at_the_phase_start_whatever_was_in_flight(in_flight):
    ack, second, processed = _second_stream(in_flight, (PHASE_START,))
    assert ack == PHASE_START  # the start's ACK announces the phase's first exposure: nothing counted lost
    assert second == list(range(PHASE_START, PHASE_START + 10))
    # the skipped frames are never exposed: the estimator sees the first stream's exposures, then the phase's
    assert processed == list(range(20 + in_flight)) + second


def test_without_phase_starts_or_past_the_last_one_the_stream_goes_on():
    ack, second, _ = _second_stream(3, ())
    assert ack == 23 and second == list(range(23, 33))
    ack, second, _ = _second_stream(3, (10,))  # the phase began before the stop: nothing to skip
    assert ack == 23 and second == list(range(23, 33))


def test_the_first_stream_is_not_moved_to_a_phase_start():
    sensor = EmulatedSensor(
        _CountingFirmware(), (SourceFrame(frame=_frame(k), r_ref=None) for k in range(60)), (0, PHASE_START)
    )
    assert sensor.handle(m.StreamControl(tag=1, enable=True)).value == 0
    assert sensor.next_stream_message().frame == 0


def test_the_bench_replay_puts_the_drift_phase_at_its_first_frame():
    """The replay: calibration phase + spare frames, then the drift phase from ``drift_first_frame``; the truth of
    each frame counter is the phase's own (the attitude of the simulator frame the sensor replays)."""
    cfg = BenchConfig(cal_frames=12, drift_frames=20, spare_frames=8, min_stars=4)
    cal, drift = simulate_phases(cfg)
    first = drift_first_frame(cfg)
    assert first == 12 + 8
    replay = concatenate_sessions(cal.session, drift.session, first)
    counters = np.unique(replay.frame)
    assert np.array_equal(counters, np.arange(first + 20 + 8))  # every exposure once, no gap between the phases
    drift_counters = counters[counters >= first]
    assert np.array_equal(drift_frame_index(cfg, drift, drift_counters), np.arange(28))
    truth = replay_truth_attitudes(cfg, cal, drift, counters)
    assert np.array_equal(truth[:first], truth_attitudes(cal))
    assert np.array_equal(truth[first:], truth_attitudes(drift))


def test_the_tracking_figure_scores_the_phase_and_its_first_read_past_it():
    """Estimates read after the stop from exposures still in flight (their number depends on the host's timing) are
    not scored, but the first read past the phase is: it is the phase's last state."""
    from hostlink.mission.summary import within_drift_phase

    cfg = BenchConfig(drift_frames=100)
    index = np.array([10, 60, 99, 130, 180, 400])
    assert within_drift_phase(cfg, index).tolist() == [True, True, True, True, False, False]
    assert within_drift_phase(cfg, np.array([104])).tolist() == [True]  # a 5-frame-like phase keeps its end read


def test_a_phase_start_without_a_replay_is_a_one_line_refusal(capsys):
    """The simulated source cycles without end: a stream restarted before a far phase start (4e9) would skip
    exposures for hours. --phase-start goes with --replay, whose length bounds the skip."""
    from hostlink.cli import main

    code = main(["emulate", "--transport", "serial", "--phase-start", "4000000000"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--phase-start goes with --replay" in err, err
