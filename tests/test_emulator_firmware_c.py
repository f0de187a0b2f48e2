"""``hostlink emulate --firmware c``: the C firmware core behind the same endpoints as the Python model. On serial,
CAN and Modbus the host's commands work against it as a user runs them: stream frames, upload a set (read back
equal), read it as the active set, and a set the sensor refuses is refused with the reference model's reason. Without
the estimator's C implementation (estimator_seam.c) the sensor answers READ_ESTIMATE with NO_ESTIMATE."""

import json
import os
import shutil
import subprocess
import sys

import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.files.params import data_file, load_params
from hostlink.files.session import read_session
from hostlink.portkit import firmware_c
from onboard.banks import params_to_table

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC") or "cc") is None, reason="no C compiler")


@pytest.fixture(scope="module", autouse=True)
def built():
    firmware_c.build_library()  # once, before the emulators start (each then loads it from the cache)


@pytest.mark.parametrize("transport", ["serial", "can", "modbus"])
def test_the_c_firmware_streams_uploads_and_refuses_as_the_python_one(transport, tmp_path):
    with running_emulator(transport, "--firmware", "c", "--sim-frames", "50", "--no-estimator") as info:
        link = info["link"]
        out = tmp_path / "s.csv"
        run = hostlink("stream", "--link", link, "--frames", "20", "--out", str(out))
        assert run.returncode == 0, run.stderr
        assert read_session(out).n_frames == 20
        camera = data_file("seed004_camera.json")
        run = hostlink("upload", str(camera), "--link", link)
        assert run.returncode == 0 and "read back equal" in run.stderr, run.stderr
        shown = hostlink("params", "--link", link)
        printed = tmp_path / "printed.json"
        printed.write_text(shown.stdout)
        assert params_to_table(load_params(printed)) == params_to_table(load_params(camera))
        bad = json.loads(camera.read_text())
        bad["principal_point_px"] = [5000.0, 530.0]
        path = tmp_path / "bad.json"
        path.write_text(json.dumps(bad))
        run = hostlink("upload", str(path), "--link", link, "--no-host-check")
        assert run.returncode == 4, run.stderr
        assert "INVALID_PARAMS" in run.stderr and "principal_point_px[0]: 5000.0 is off the detector" in run.stderr
        if not firmware_c.estimator_available():
            run = hostlink("monitor", "--link", link, "--count", "1", "--every-frames", "5")
            assert run.returncode == 0 and "no estimate" in run.stdout, run.stdout  # Modbus carries no NAK text


def test_without_a_compiler_the_c_firmware_is_a_one_line_error():
    env = {**os.environ, "CC": "no-such-compiler"}
    run = subprocess.run(
        [sys.executable, "-m", "hostlink.cli", "emulate", "--transport", "serial", "--firmware", "c"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "no C compiler found ('no-such-compiler' is not on PATH)" in run.stderr
