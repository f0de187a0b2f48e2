"""The bench accounts for every frame of a streaming phase, and a drift phase that fell short is not a success."""

import json

import pytest

from hostlink.errors import LinkError
from hostlink.mission.config import BenchConfig, spare_frames
from hostlink.mission.summary import StreamCount, incomplete_reason


def test_frames_the_sensor_took_are_received_lost_or_in_flight():
    count = StreamCount(expected=600, received=600, lost_on_link=4, exposures=650, held_at_start=1456)
    assert count.complete and count.in_flight_at_stop == 46
    assert count.as_dict()["frames_in_flight_at_stop"] == 46 and count.as_dict()["complete"] is True


def test_a_drift_phase_whose_replay_ran_out_says_where_its_frames_went():
    cal = StreamCount(expected=600, received=600, lost_on_link=0, exposures=1342)
    drift = StreamCount(
        expected=3000, received=2514, lost_on_link=0, exposures=2514, held_at_start=2514, ended_early=True
    )
    assert not drift.complete
    reason = incomplete_reason(drift, cal, 256)
    assert reason.startswith("the sensor sent 2514 of the 3000 drift frames before its replay ran out (256 spare")
    assert "742 in flight when the calibration stream stopped" in reason
    assert incomplete_reason(cal, None, 256) is None  # a complete phase needs no reason


def test_default_spare_frames_cover_a_host_reading_at_a_third_of_the_link_rate():
    # a host at a fraction q of the link's frame rate is cal_frames (1/q - 1) frames behind at the calibration stop
    cfg = BenchConfig(cal_frames=600)
    q = 1 / 3
    assert spare_frames(cfg) >= round(cfg.cal_frames * (1 / q - 1))
    assert spare_frames(BenchConfig(cal_frames=60)) == 256 and spare_frames(BenchConfig(spare_frames=7)) == 7


@pytest.mark.slow  # the whole mission end to end (issue 29: the fast lane is pytest -m 'not slow')
def test_a_bench_whose_drift_phase_falls_short_writes_its_counts_and_fails(tmp_path):
    from hostlink.api import run_bench

    # no spare frames and every 10th stream message lost on the line: the calibration phase takes more than its 60
    # frames from the replay, so the drift phase cannot get its 40, whatever the host's speed
    cfg = BenchConfig(
        out_dir=tmp_path,
        cal_frames=60,
        drift_frames=40,
        spare_frames=0,
        emulator_args=("--drop-every", "10"),
    )
    with pytest.raises(LinkError, match="the drift phase is incomplete: the sensor sent [0-9]+ of the 40 drift frames"):
        run_bench(cfg, say=lambda text: None, show_progress=False)
    summary = json.loads((tmp_path / "summary.json").read_text())
    track = summary["drift_tracking"]
    assert summary["success"] is False and track["complete"] is False and track["stream_ended_early"] is True
    assert track["frames_expected"] == 40 and track["frames_received"] < 40
    cal = summary["calibration_stream"]
    assert cal["frames_received"] == 60 and cal["frames_lost_on_link"] >= 5  # every 10th message of >= 60 frames
    # every frame the sensor took is accounted for: received, lost on the link, or in flight at a stop
    for phase in (cal, track):
        assert phase["sensor_exposures"] == (
            phase["frames_received"] + phase["frames_lost_on_link"] + phase["frames_in_flight_at_stop"]
        )
    assert (
        cal["sensor_frames_held_at_start"] == 100
        and track["sensor_frames_held_at_start"] == 100 - cal["sensor_exposures"]
    )
