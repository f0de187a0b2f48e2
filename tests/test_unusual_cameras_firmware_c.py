"""The C firmware core and the Python reference model on detectors wider than the built-in ones: every size the
parameter checks accept starts an onboard estimator in both, and the checks refuse, in the same words, a detector
whose float32 estimator would overflow. The C estimator seam once refused a side above 65535 px, so a sensor with a
70000 px wide strip ran no estimator in C (READ_ESTIMATE: "no active parameter set to start from") while the Python
model tracked it; a farthest corner beyond ~3.2e5 px from the principal point overflowed the float32 Jacobian (u r^6)
and the Python model faulted on every frame while the C core reported NaN estimates: such sets are now refused
(onboard.params.MAX_CORNER_RADIUS_PX, 2^18 px)."""

import os
import shutil

import numpy as np
import pytest

from hostlink.emulator.setup import c_firmware, sensor_banks
from hostlink.portkit import firmware_c
from onboard import banks
from onboard.camera import pixels_to_unit
from onboard.firmware import Firmware, RecursiveEstimator
from onboard.params import ESTIMATE_NAMES, MAX_CORNER_RADIUS_PX, CameraParams, ParameterError, validate_params
from onboard.recursive import RecursiveConfig
from protocol import messages as m

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC") or "cc") is None, reason="no C compiler")

#: Stars per frame and frames: enough for the estimator to update from a cold start.
N_STARS, N_FRAMES = 12, 3


def run_both(nominal: CameraParams, precision: str) -> tuple[m.Message, m.Message, object, object]:
    """The same frames (centroids on the whole detector, exact references) to both firmwares; their estimate replies
    and counters."""
    c = c_firmware(nominal, precision=precision)
    py = Firmware(
        sensor_banks(nominal, None, None), RecursiveEstimator(ESTIMATE_NAMES, RecursiveConfig(), precision=precision)
    )
    rng = np.random.default_rng(1)
    w, h = nominal.image_size_px
    for k in range(N_FRAMES):
        x, y = rng.uniform(0, w - 1, N_STARS), rng.uniform(0, h - 1, N_STARS)
        frame = m.CentroidFrame(
            frame=k,
            t_us=k * 100_000,
            star_id=np.arange(1, N_STARS + 1, dtype=np.uint32),
            x_px=x,
            y_px=y,
            mag=np.full(N_STARS, 5.0),
        )
        r = pixels_to_unit(x, y, nominal.model_vector())
        py.process_frame(frame, r)
        c.process_frame(frame, r)
    return py.handle(m.ReadEstimate()), c.handle(m.ReadEstimate()), py.counters, c.counters


@pytest.mark.parametrize("precision", ["float32", "fixed"])
@pytest.mark.parametrize("width", [65535, 65536, 70000, 2 * MAX_CORNER_RADIUS_PX - 1024])
def test_a_detector_wider_than_65535_px_runs_the_estimator_in_c_as_in_python(width, precision):
    # F = the width in pixels: a 53 deg field across the strip
    nominal = CameraParams(width * 5.0 / 1000, 5.0, (width / 2 - 0.5, 255.5), (width, 512))
    py, c, py_counters, c_counters = run_both(nominal, precision)
    assert isinstance(py, m.Estimate) and isinstance(c, m.Estimate), (py, c)
    assert c.n_updates == py.n_updates == N_FRAMES and c_counters == py_counters
    # the float32 filters differ in operation order only: far below each estimate's own 1-sigma
    assert np.all(np.abs(np.subtract(c.values, py.values)) <= 1e-2 * np.asarray(py.sigma)), (c.values, py.values)


@pytest.mark.parametrize(
    "size, pp",
    [((2 * MAX_CORNER_RADIUS_PX + 2, 512), None), ((1 << 20, 512), None), ((300_000, 300_000), (-0.5, -0.5))],
)
def test_a_detector_whose_float32_jacobian_would_overflow_is_refused_in_one_line_alike(size, pp):
    w, h = size
    pp = pp or (w / 2 - 0.5, h / 2 - 0.5)
    params = CameraParams(w * 5.0 / 1000, 5.0, pp, size)
    with pytest.raises(ParameterError, match="beyond 262144 px") as refused:
        validate_params(params)  # the host's check, float64: the same rule
    assert "\n" not in str(refused.value)
    table = banks.params_to_table(params)
    refusal = banks.check_table(table, None)
    assert refusal is not None and refusal.text == str(refused.value)
    assert firmware_c.check_table_c(table, None) == m.nak_text_bytes(refusal.text).decode()
