"""``hostlink bench``: the main job end to end against an emulated sensor over a real link (serial pty)."""

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # the whole mission end to end (issue 29: the fast lane is pytest -m 'not slow')


@pytest.fixture(scope="module")
def bench_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "hostlink.cli",
            "bench",
            "--out",
            str(out),
            "--quiet",
            "--frames",
            "300",
            "--drift-frames",
            "1500",
            "--seed",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    return out, json.loads((out / "summary.json").read_text()), run.stdout


def test_calibrated_residual_is_at_the_noise_floor(bench_report):
    _, summary, _ = bench_report
    after, floor = summary["residual_after"]["rms_px"], summary["noise_floor_rms_px"]
    # ~4500 stars x 2 axes: the RMS of pure noise scatters by ~1 % (1/sqrt(2N)); 5 % is 5 sigma, and any
    # unmodelled distortion of the true camera (0.3-1.5 px before calibration) would show far above it
    assert after <= 1.05 * floor
    assert summary["residual_before"]["rms_px"] > 10 * after


def test_uploaded_parameters_are_verified_by_read_back(bench_report):
    _, summary, _ = bench_report
    assert summary["upload"]["read_back_equal_float32"] is True
    assert summary["upload"]["generation"] == 2
    assert summary["link"]["lost_messages"] == 0


def test_calibrated_parameters_are_within_their_stated_uncertainty(bench_report):
    _, summary, _ = bench_report
    p = summary["parameters"]
    # 4 sigma: a false failure once in ~16000 runs per parameter, for a Gaussian estimate with honest sigma
    assert abs(p["error_focal_um"]) < 4 * p["sigma"]["focal_length_mm"] * 1000
    for k in range(2):
        assert abs(p["error_principal_point_px"][k]) < 4 * p["sigma"]["principal_point_px"][k]


def test_onboard_estimator_tracks_the_focal_drift(bench_report):
    _, summary, _ = bench_report
    track = summary["drift_tracking"]
    assert track["frames_streamed"] == 1500  # the replay's spare frames cover what is in flight between the phases
    assert summary["success"] is True and track["complete"] is True and track["frames_expected"] == 1500
    # the sensor's budget gives every 1 s exposure to the estimator, however busy the host (issue 10: >= 90 %)
    assert track["estimator_updates"] == track["sensor_exposures"] >= 1500
    # issue 4's bar is 1 um RMS after 3000 frames; over this shorter 1500-frame run the drift detector switches on
    # after ~400 frames, so allow 1.5 um, still well below the 4.2 um RMS of the drift itself
    assert track["focal_error_rms_um_converged"] < 1.5
    assert track["focal_error_rms_um_converged"] < 0.5 * track["focal_true_rms_deviation_um"]
    # the drift stream begins at the drift phase's first exposure, however many the sensor took while the host stopped
    # the calibration stream: the truth, the filter's restart and the scored window are aligned (issue 27, CAN)
    assert track["first_frame_drift_index"] == 0


def test_report_has_summary_plots_and_a_terminal_table(bench_report):
    out, _, stdout = bench_report
    for name in ("residuals-before.png", "residuals-after.png", "estimator-convergence.png", "drift-tracking.png"):
        assert (out / name).stat().st_size > 10_000, name
    assert "residual RMS (px)" in stdout and "focal drift tracking" in stdout


def test_the_step_counter_counts_each_of_its_steps_once_in_order(bench_report):
    """Issue 31: the bench said [1/6] .. [5/6]; every step it announces is now counted, [1/6] to [6/6]."""
    import re

    assert re.findall(r"^\[(\d)/(\d)\]", bench_report[2], re.MULTILINE) == [(str(k), "6") for k in range(1, 7)]


def test_bad_bench_option_is_one_line_and_non_zero(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", "bench", "--out", str(tmp_path), "--noise-px", "-1"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1 and "--noise-px" in run.stderr


def test_a_sensor_whose_estimator_never_updates_is_reported_as_such_not_as_nan(tmp_path):
    from hostlink.api import BenchConfig, run_bench
    from hostlink.mission.summary import summary_table

    cfg = BenchConfig(out_dir=tmp_path, cal_frames=60, drift_frames=30, emulator_args=("--no-estimator",))
    summary = run_bench(cfg, say=lambda text: None, show_progress=False)
    track = summary["drift_tracking"]
    assert track["estimator_updates"] == 0 and track["sensor_exposures"] >= 29
    assert track["focal_error_rms_um_converged"] is None
    assert track["not_tracked_because"].startswith("the onboard estimator made no update in the drift phase")
    printed = " ".join(" ".join(row) for row in summary_table(summary))
    assert "nan" not in printed.lower() and "--drift-frames" not in printed
