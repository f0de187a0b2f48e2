"""``hostlink upload`` of implausible parameter sets against the emulator process (issue 15): OpenCV-sized
distortion, a huge one-to-one distortion and a focal length far from the sensor's design are refused by the host
check (one line, exit 2) and, with the host check bypassed, by the sensor itself with the rule named (exit 4);
the seed-004 and a realistic all-terms camera are committed."""

import json

import pytest
from emulator_fixtures import hostlink

from hostlink.emulator.process import EmulatorProcess
from hostlink.files.params import data_file

FAST = ("--no-estimator", "--sim-frames", "5")
SEED004 = json.loads(data_file("seed004_camera.json").read_text())
REALISTIC = dict(SEED004, distortion=dict(k1=-2.0e-10, k2=3.5e-15, k3=-4e-21, p1=2e-7, p2=-1.5e-7, s1=1e-7, s2=-2e-7))


@pytest.fixture(scope="module")
def sensor(tmp_path_factory):
    flash = tmp_path_factory.mktemp("flash") / "sensor.img"
    with EmulatorProcess("serial", FAST, flash_path=flash) as emulator:
        yield emulator.link


def one_line(text):
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def write(tmp_path, doc, name="set.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return str(path)


@pytest.mark.parametrize(
    ("distortion", "focal_mm", "host_rule", "sensor_rule"),
    [
        ({"k1": -0.12, "k2": 0.3}, 70.2262, "radial mapping is not one-to-one", "radial mapping is not one-to-one"),
        ({"k1": -0.12}, 70.2262, "implausible: displacement", "implausible: displacement"),
        ({"k1": -2e-10}, 35.0, "focal_length_mm: implausible", "focal_length_mm: implausible"),
    ],
    ids=["opencv-sized", "huge-one-to-one", "focal-half-the-design"],
)
def test_an_implausible_set_is_refused_by_the_host_and_by_the_sensor_naming_the_rule(
    sensor, tmp_path, distortion, focal_mm, host_rule, sensor_rule
):
    path = write(tmp_path, dict(SEED004, focal_length_mm=focal_mm, distortion=distortion))
    before = hostlink("params", "--link", sensor).stdout
    run = hostlink("upload", path, "--link", sensor)
    assert run.returncode == 2 and host_rule in one_line(run.stderr)
    run = hostlink("upload", path, "--link", sensor, "--no-host-check")
    line = one_line(run.stderr)
    assert run.returncode == 4 and "INVALID_PARAMS" in line and sensor_rule in line
    assert hostlink("params", "--link", sensor).stdout == before  # nothing was committed


@pytest.mark.parametrize("doc", [SEED004, REALISTIC], ids=["seed004", "realistic-all-terms"])
def test_real_cameras_are_committed(sensor, tmp_path, doc):
    run = hostlink("upload", write(tmp_path, doc), "--link", sensor)
    assert run.returncode == 0 and "read back equal" in one_line(run.stderr)
