"""The C firmware core and the Python reference model on detectors wider than the built-in ones: every size the
parameter checks accept starts an onboard estimator in both, and the checks refuse, in the same words, a detector
whose float32 estimator would overflow. The C estimator seam once refused a side above 65535 px, so a sensor with a
70000 px wide strip ran no estimator in C (READ_ESTIMATE: "no active parameter set to start from") while the Python
model tracked it; a farthest corner beyond ~3.2e5 px from the principal point overflowed the float32 Jacobian (u r^6)
and the Python model faulted on every frame while the C core reported NaN estimates: such sets are now refused
(onboard.params.MAX_CORNER_RADIUS_PX, 2^18 px)."""

import os
import shutil
from dataclasses import replace

import numpy as np
import pytest

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor
from hostlink.emulator.setup import c_firmware, sensor_banks
from hostlink.links.base import CommandRefused
from hostlink.links.operations import safe_upload
from hostlink.portkit import firmware_c
from hostlink.portkit.firmware_c import CFirmware
from onboard import banks
from onboard.camera import pixels_to_unit
from onboard.firmware import Firmware, RecursiveEstimator
from onboard.params import (
    ESTIMATE_NAMES,
    MAX_CORNER_RADIUS_PX,
    CameraParams,
    Distortion,
    ParameterError,
    PlausibilityLimits,
    validate_params,
)
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
        sensor_banks(nominal, None, None, precision == "fixed"),
        RecursiveEstimator(ESTIMATE_NAMES, RecursiveConfig(), precision=precision),
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


# ------------------------------------------------------------------------------------ the fixed-point sensor's range
#: A 8192 x 8192 px, 5 um detector designed at F = 2^20 px, the longest focal length its fixed-point formats take,
#: and one designed at F = S/8 = 1024 px, the shortest.
LONG_DESIGN = CameraParams(float(1 << 20) * 5.0 / 1000, 5.0, (4095.5, 4095.5), (8192, 8192))
SHORT_DESIGN = replace(LONG_DESIGN, focal_length_mm=1024 * 5.0 / 1000)


def sensors(design: CameraParams, limits: PlausibilityLimits, precision: str):
    """The Python model's sensor and the C core's, same identity and factory set ``design``, under ``limits``."""
    python = Firmware(
        banks.factory_store(design, limits=limits, identity=banks.seeded_identity(3)),
        RecursiveEstimator(ESTIMATE_NAMES, RecursiveConfig(), precision=precision),
    )
    identity = banks.seeded_identity(3)
    c = CFirmware(banks.RamFlash(), identity, limits, factory=design, estimate_mask=0x3FF, precision=precision)
    return python, c


def upload_refusal(firmware, params: CameraParams) -> str | None:
    """The sensor's refusal of a safe upload of ``params`` (the host's own check skipped), None when committed."""
    try:
        safe_upload(LoopbackLink(EmulatedSensor(firmware, iter(())), timeout_s=0.5), params, host_check=False)
    except CommandRefused as exc:
        return exc.text
    return None


@pytest.mark.parametrize(
    "design, params, reason",
    [
        (LONG_DESIGN, replace(LONG_DESIGN, focal_length_mm=LONG_DESIGN.focal_length_mm * 1.03), "above 2^20"),
        (SHORT_DESIGN, replace(SHORT_DESIGN, focal_length_mm=SHORT_DESIGN.focal_length_mm * 0.99), "below S/8 = 1024"),
        (LONG_DESIGN, replace(LONG_DESIGN, distortion=Distortion(k1=-1.5 / 0.5 / 8192.0**2)), "up to 150 % of"),
    ],
    ids=["F-above-2^20", "F-below-S/8", "distortion-beyond-the-radius"],
)
def test_a_fixed_point_sensor_refuses_an_upload_outside_its_range_in_the_same_words_in_c_and_python(
    design, params, reason
):
    """A set that passes every other rule (the focal length within 5 % of a design at the edge of the range; the
    distortion under a 500 % displacement bound, so that only the fixed range can refuse it) is refused at
    STAGE_VERIFY by a fixed-point sensor, in one line, the same in both; before, it was committed and every frame
    then counted as an estimator fault. A float32 sensor commits it."""
    limits = PlausibilityLimits(design.focal_length_mm, max_distortion_fraction=5.0)
    texts = [upload_refusal(fw, params) for fw in sensors(design, replace(limits, fixed_point=True), "fixed")]
    assert texts[0] == texts[1], texts
    assert texts[0].startswith("fixed point: outside the sensor's range: ") and reason in texts[0], texts[0]
    assert "\n" not in texts[0]
    assert [upload_refusal(fw, params) for fw in sensors(design, limits, "float32")] == [None, None]


def test_the_sensor_checks_name_the_fixed_range_alike_for_every_rule_at_the_edges():
    """banks.check_table and the C core's params_check_table under a fixed-point sensor's limits, text for text, on
    focal lengths around both bounds and detectors of every shift (the default 5 % distortion bound)."""
    refused = 0
    for side in (256, 2047, 2048, 2049, 8192, 131072):
        for f_px in (side / 16, 2.0 ** ((side - 1).bit_length() - 3), 1048576.0, 1048577.0, 1.05 * 1048576.0):
            params = CameraParams(f_px * 5.0 / 1000, 5.0, (side / 2 - 0.5, side / 2 - 0.5), (side, side))
            limits = PlausibilityLimits(params.focal_length_mm, fixed_point=True)
            table = banks.params_to_table(params)
            refusal = banks.check_table(table, limits)
            want = None if refusal is None else m.nak_text_bytes(refusal.text).decode()
            assert firmware_c.check_table_c(table, limits) == want, (side, f_px)
            refused += refusal is not None
    assert refused >= 12  # both bounds refused at every size (the S/16 and above-2^20 cases)
