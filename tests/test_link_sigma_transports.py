"""The 1-sigma prior travels with the parameter set on every transport (serial, CAN ISO-TP, Modbus TCP and RTU), as a
user drives it: ``hostlink upload`` sends the file's sigma, ``hostlink params`` prints it back (float32, bit for bit),
a sigma the sensor refuses comes back with its field name on one line, and ``hostlink accept`` commits the estimate
with its own sigma."""

import json

import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.files.params import data_file
from onboard.prior import sigma_from_dict

SIGMA = {
    "focal_length_mm": 7e-4,
    "principal_point_px": [1.3, 1.29],
    "distortion": {"k1": 1.4e-10, "k2": 5.8e-16, "k3": None, "p1": 2.2e-8, "p2": 2.1e-8, "s1": 2e-8, "s2": 2e-8},
    "fixed": [],
    "unobservable": ["k3"],
}
TRANSPORTS = [("serial", ()), ("can", ("--bitrate", "500000")), ("modbus", ()), ("modbus-rtu", ())]


@pytest.fixture(scope="module", params=TRANSPORTS, ids=[t for t, _ in TRANSPORTS])
def sensor_link(request):
    transport, extra = request.param
    with running_emulator(
        "modbus" if transport.startswith("modbus") else transport, "--sim-frames", "60", *extra
    ) as info:
        yield info["link_rtu" if transport == "modbus-rtu" else "link"]


def one_line(text):
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def test_upload_sends_the_sigma_and_params_prints_it_back(sensor_link, tmp_path):
    doc = json.loads(data_file("seed004_camera.json").read_text())
    doc["sigma"] = SIGMA
    path = tmp_path / "calibrated.json"
    path.write_text(json.dumps(doc))
    run = hostlink("upload", str(path), "--link", sensor_link)
    assert run.returncode == 0, run.stderr
    assert "sigma prior for 9 of 10 parameters" in one_line(run.stderr)
    shown = hostlink("params", "--link", sensor_link)
    assert shown.returncode == 0, shown.stderr
    printed = json.loads(shown.stdout)["sigma"]
    assert printed["distortion"]["k3"] is None  # unknown stays unknown
    np.testing.assert_array_equal(
        sigma_from_dict(printed).astype(np.float32), sigma_from_dict(SIGMA).astype(np.float32)
    )  # float32, bit for bit (NaN = NaN)


def test_a_refused_sigma_names_its_field_on_one_line(sensor_link, tmp_path):
    doc = json.loads(data_file("seed004_camera.json").read_text())
    doc["sigma"] = dict(SIGMA, principal_point_px=[-1.0, 1.29])
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    before = hostlink("params", "--link", sensor_link).stdout
    run = hostlink("upload", str(path), "--link", sensor_link, "--no-host-check")  # the sensor decides
    assert run.returncode == 4
    line = one_line(run.stderr)
    assert "INVALID_PARAMS" in line and "sigma.principal_point_px[0]" in line
    assert hostlink("params", "--link", sensor_link).stdout == before  # the old set is still active
    run = hostlink("upload", str(path), "--link", sensor_link)  # the host's own check refuses first
    assert run.returncode == 2 and "sigma.principal_point_px[0]" in one_line(run.stderr)


def test_accept_commits_the_estimate_with_its_own_sigma(sensor_link, tmp_path):
    monitor = hostlink("monitor", "--link", sensor_link, "--count", "1", "--interval", "0.3", "--json")
    assert monitor.returncode == 0, monitor.stderr
    out = tmp_path / "accepted.json"
    # forced: a few updates are far from converged; this test is about the sigma travelling, not about convergence
    run = hostlink("accept", "--link", sensor_link, "--out", str(out), "--force")
    assert run.returncode == 0, run.stderr
    accepted = json.loads(out.read_text())
    shown = json.loads(hostlink("params", "--link", sensor_link).stdout)
    assert accepted == shown and set(shown["sigma"]) == {"focal_length_mm", "principal_point_px", "distortion"}
    assert all(v is not None and v > 0 for v in shown["sigma"]["principal_point_px"])
