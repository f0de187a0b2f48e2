"""The bench's nominal camera: given, built in, or the camera's design values; never one of another detector."""

import pytest

from hostlink.api import BenchConfig, design_nominal, load_params
from hostlink.errors import UserError
from hostlink.mission.config import BENCH_TRUE_CAMERA, bench_nominal
from onboard.params import CameraParams, Distortion

#: 1280 x 320 px, 6 um: a detector unlike the built-in 1024 x 1024 px, 12 um one.
STRIP = CameraParams(25.0, 6.0, (900.0, 100.0), (1280, 320), Distortion(k1=-3.5e-9))


def test_the_built_in_camera_gets_the_shipped_design_values():
    assert bench_nominal(BenchConfig()) == load_params("builtin:seed004_nominal")
    assert BENCH_TRUE_CAMERA.image_size_px == bench_nominal(BenchConfig()).image_size_px


def test_another_camera_without_a_nominal_gets_its_own_design_values():
    nominal = bench_nominal(BenchConfig(camera=STRIP))
    assert nominal == design_nominal(STRIP)
    assert nominal.principal_point_px == (639.5, 159.5) and nominal.distortion == Distortion()


def test_a_nominal_of_another_detector_is_a_one_line_error():
    with pytest.raises(UserError, match="same detector"):
        bench_nominal(BenchConfig(nominal=design_nominal(STRIP)))
