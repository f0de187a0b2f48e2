"""The sensor's precision is one option of its firmware (``RecursiveEstimator(precision=...)``, ``hostlink emulate
--precision``): a fixed-point sensor (no FPU: integer front end, soft-float32 filter) streams over a link and its
onboard estimate follows the float32 sensor's, both held against float64 of the same code and against the truth."""

import numpy as np
import pytest

from hostlink.calibration.replay import replay_session
from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.emulator.setup import DEFAULT_CAMERA, DEFAULT_NOMINAL, build_sensor
from hostlink.errors import UserError
from hostlink.files.params import load_params, save_params
from hostlink.links.operations import stream_frames
from hostlink.sky.simulate import SimConfig, simulate
from onboard import banks, recursive
from onboard.firmware import Firmware, RecursiveEstimator
from onboard.fixedpoint import FixedRangeError
from onboard.params import CameraParams
from onboard.recursive import RecursiveConfig
from protocol.messages import CentroidFrame

N_FRAMES = 400  # past the 300-frame burn-in: every parameter, distortion included, is estimated


def _stream(precision: str, dtype=np.float32):
    """A sensor in ``precision`` (``dtype`` float64: the host's reference of the same code) streams N_FRAMES frames
    of the simulated seed-004 camera over an in-process link; returns its estimator state and the estimate read."""
    sim = simulate(SimConfig(camera=load_params(DEFAULT_CAMERA), frames=N_FRAMES, noise_px=0.05, seed=3))
    seam = RecursiveEstimator(config=RecursiveConfig(centroid_noise_px=0.05), dtype=dtype, precision=precision)
    firmware = Firmware(banks.factory_store(load_params(DEFAULT_NOMINAL)), seam)
    link = LoopbackLink(EmulatedSensor(firmware, session_frames(sim.session)))
    assert len(stream_frames(link, N_FRAMES).frames) == N_FRAMES
    return firmware._est_state, link.read_estimate()


@pytest.fixture(scope="module")
def runs():
    return {p: _stream(p) for p in ("float32", "fixed")} | {"float64": _stream("float32", np.float64)}


def test_the_fixed_point_sensor_over_a_link_estimates_as_float64_of_the_same_code(runs):
    ref, _ = runs["float64"]
    sd = np.sqrt(np.diag(recursive.covariance(ref)))
    for precision in ("float32", "fixed"):
        state, estimate = runs[precision]
        assert estimate.n_updates == N_FRAMES  # every frame reached the estimator, in either precision
        diff = (recursive.state_vector(state) - recursive.state_vector(ref)) / sd
        # measured 0.4 % of sigma for both (fixed: the wire's 2^-10 px rounding, 2.8e-4 px RMS against 0.05 px
        # noise, plus the front end's 1e-5 px); 2 % is 5x that and 1/50 of what the data can resolve
        assert np.all(np.abs(diff) < 0.02), (precision, diff)


def test_the_fixed_point_sensors_error_against_truth_is_within_5_percent_of_the_float32_sensors(runs):
    truth = load_params(DEFAULT_CAMERA).model_vector()
    ref, _ = runs["float32"]
    info = np.linalg.inv(recursive.covariance(ref))
    chi2 = {}
    for precision in ("float32", "fixed"):
        err = recursive.state_vector(runs[precision][0]) - truth
        chi2[precision] = float(err @ info @ err)
    # issue 14's acceptance (1.05x the float32 error), in the metric the filter's covariance defines: measured 1.001
    assert np.sqrt(chi2["fixed"] / chi2["float32"]) < 1.05, chi2


def test_the_estimate_read_over_the_link_is_the_sensors_state_in_float32(runs):
    state, estimate = runs["fixed"]
    np.testing.assert_array_equal(
        np.asarray(estimate.values, dtype=np.float32), recursive.current_params(state).vector(np.float32)
    )


def test_replay_and_the_firmware_run_the_same_fixed_point_code():
    sim = simulate(SimConfig(camera=load_params(DEFAULT_CAMERA), frames=40, noise_px=0.05, seed=5))
    nominal = load_params(DEFAULT_NOMINAL)
    replayed = replay_session(sim.session, nominal, precision="fixed")
    sensor = build_sensor(sim_frames=40, precision="fixed", seed=5)
    link = LoopbackLink(sensor)
    stream_frames(link, 40)
    # the same frames, the same integers, the same float32 filter: bit for bit
    np.testing.assert_array_equal(
        recursive.state_vector(replayed.state), recursive.state_vector(sensor.firmware._est_state)
    )


def test_an_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision"):
        RecursiveEstimator(precision="float16")
    with pytest.raises(UserError, match="--precision"):
        build_sensor(sim_frames=5, precision="double")


def test_a_nominal_outside_the_fixed_point_range_is_a_one_line_error(tmp_path):
    wide = CameraParams(  # F = 100 px < S/8 = 128 px: a field wider than the formats are proved for
        focal_length_mm=1.2, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
    )
    save_params(tmp_path / "wide.json", wide)
    with pytest.raises(UserError, match="outside the fixed-point range") as exc:
        build_sensor(nominal=str(tmp_path / "wide.json"), sim_frames=5, precision="fixed")
    assert "\n" not in str(exc.value)


def test_a_frame_outside_the_fixed_point_range_is_counted_as_a_fault_and_the_sensor_runs_on():
    class _OutOfRange(RecursiveEstimator):
        def update(self, *args):
            raise FixedRangeError("distortion correction beyond the radius")

    fw = Firmware(banks.factory_store(load_params(DEFAULT_NOMINAL)), _OutOfRange(precision="fixed"))
    frame = CentroidFrame(
        frame=1,
        t_us=0,
        star_id=np.array([1, 2, 3], dtype=np.uint32),
        x_px=np.array([100.0, 500.0, 900.0]),
        y_px=np.array([100.0, 800.0, 300.0]),
        mag=np.full(3, np.nan),
    )
    assert fw.process_frame(frame, np.eye(3))
    assert fw.counters.estimator_faults == 1 and fw._est_state is not None  # restarted from the active set


def test_emulate_and_bench_take_the_precision_option_float32_by_default():
    from hostlink.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["emulate", "--transport", "can", "--precision", "fixed"]).precision == "fixed"
    assert parser.parse_args(["emulate", "--transport", "can"]).precision == "float32"
    assert parser.parse_args(["bench", "--precision", "fixed"]).precision == "fixed"
    assert parser.parse_args(["bench"]).precision == "float32"


@pytest.mark.slow  # the whole mission end to end (issue 29: the fast lane is pytest -m 'not slow')
def test_bench_runs_the_whole_mission_on_the_fixed_point_sensor(tmp_path):
    import json
    import subprocess
    import sys

    out = tmp_path / "bench"
    args = ["bench", "--precision", "fixed", "--out", str(out), "--quiet", "--frames", "300", "--drift-frames", "1500"]
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", *args, "--seed", "3"], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["precision"] == "fixed" and "fixed sensor" in run.stdout
    track = summary["drift_tracking"]
    assert track["estimator_updates"] == track["sensor_exposures"] >= 1500  # every exposure, as the float32 sensor
    assert summary["upload"]["read_back_equal_float32"] is True
    # the bar of tests/test_bench_end_to_end.py for this 1500-frame run (the drift detector needs ~400 frames):
    # 1.5 um, well under the drift's own 4.2 um RMS (measured: 0.66 um fixed, 0.66 um float32 at 3000 frames)
    assert track["focal_error_rms_um_converged"] < 1.5
