"""The six-step safe upload over the Link interface (in-process loopback: real codecs and firmware, no port):
success reads back equal to float32; an interrupted, corrupted or refused upload leaves the old set active."""

import dataclasses
import math

import numpy as np
import pytest

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.errors import LinkError, UserError
from hostlink.links.base import CommandRefused
from hostlink.links.operations import (
    accept_estimate,
    float32_equal,
    params_float32_dict,
    read_active_params,
    safe_upload,
    stream_frames,
)
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
from onboard import banks
from onboard.firmware import (
    ACCEPT_MIN_UPDATES,
    Firmware,
    RecursiveEstimator,
    estimate_convergence,
    estimate_to_params,
)
from onboard.params import CameraParams, params_from_dict
from protocol import messages as m

NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)
CAMERA = seed004_camera()


def sensor(estimator=None, source=()):
    return EmulatedSensor(Firmware(banks.factory_store(NOMINAL), estimator), iter(source))


def test_upload_reads_back_equal_to_float32_under_a_new_generation():
    s = sensor()
    steps = []
    result = safe_upload(LoopbackLink(s), CAMERA, step=lambda k, text: steps.append(k))
    assert steps == [1, 2, 3, 4, 5, 6]
    assert result.generation == 2 and float32_equal(result.active, CAMERA)
    active = read_active_params(LoopbackLink(s))
    assert active.generation == 2 and float32_equal(active.params, CAMERA)
    # what `hostlink params` prints reads back as the same float32 set
    assert float32_equal(params_from_dict(params_float32_dict(active.params)), CAMERA)


@pytest.mark.parametrize("lost_chunk", [0, 1, 3])
def test_upload_interrupted_while_staging_leaves_the_old_set_active(lost_chunk):
    s = sensor()
    seen = {"chunks": 0}

    def drop(data):
        if data[0] == m.MsgType.STAGE_CHUNK:
            seen["chunks"] += 1
        if seen["chunks"] > lost_chunk:
            return None  # the line dies here: this chunk and everything after it (repeats too) are lost
        return data

    with pytest.raises(LinkError, match="no reply to STAGE_CHUNK"):
        safe_upload(LoopbackLink(s, timeout_s=0.05, tamper=drop), CAMERA)
    assert read_active_params(LoopbackLink(s)).generation == 1


def test_host_killed_between_verify_and_commit_leaves_the_old_set_active():
    s = sensor()
    link = LoopbackLink(s)
    table = banks.params_to_table(CAMERA)
    link.stage_begin(len(table))
    for off in range(0, len(table), 16):
        link.stage_chunk(off, table[off : off + 16])
    link.stage_verify(banks.crc32(table))
    link.close()  # the host is gone before step 5
    fresh = LoopbackLink(s)
    assert fresh.status().stage_state == m.StageState.VERIFIED
    active = read_active_params(fresh)
    assert active.generation == 1 and float32_equal(active.params, NOMINAL)


def test_a_chunk_corrupted_in_transit_is_caught_by_the_crc_and_nothing_commits():
    s = sensor()

    def flip(data):
        if data[0] == m.MsgType.STAGE_CHUNK and data[3:5] == b"\x10\x00":  # the chunk at offset 16
            data = data[:-1] + bytes([data[-1] ^ 0x04])
        return data

    with pytest.raises(CommandRefused) as info:
        safe_upload(LoopbackLink(s, tamper=flip), CAMERA)
    assert info.value.code == m.NakCode.BAD_CRC
    assert read_active_params(LoopbackLink(s)).generation == 1


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"focal_length_mm": math.nan}, "focal_length_mm"),
        ({"focal_length_mm": -1.0}, "focal_length_mm"),
        ({"principal_point_px": (-3.0, 500.0)}, "principal_point_px[0]"),
        ({"distortion": dataclasses.replace(CAMERA.distortion, k1=1e-5)}, "distortion"),
    ],
    ids=["nan", "negative-focal", "off-detector", "non-monotonic"],
)
def test_the_sensor_refuses_a_bad_set_with_code_and_reason_on_one_line(change, field):
    s = sensor()
    with pytest.raises(CommandRefused) as info:
        safe_upload(LoopbackLink(s), dataclasses.replace(CAMERA, **change), host_check=False)
    exc = info.value
    assert exc.code == m.NakCode.INVALID_PARAMS and exc.text.startswith(field)
    assert str(exc).startswith("sensor refused STAGE_VERIFY: INVALID_PARAMS: ") and "\n" not in str(exc)
    assert read_active_params(LoopbackLink(s)).generation == 1


def test_the_host_check_refuses_before_anything_is_sent():
    s = sensor()
    link = LoopbackLink(s)
    with pytest.raises(UserError, match="focal_length_mm"):
        safe_upload(link, dataclasses.replace(CAMERA, focal_length_mm=-1.0))
    assert link.stats.tx_bytes == 0


def test_accept_commits_the_onboard_estimate_through_the_safe_path():
    sim = simulate(SimConfig(camera=CAMERA, frames=20, noise_px=0.05, seed=9))
    s = sensor(RecursiveEstimator(), session_frames(sim.session))
    link = LoopbackLink(s)
    got = stream_frames(link, 15)
    assert len(got.frames) == 15
    estimate = link.read_estimate()
    result, used = accept_estimate(link, force=True)  # 15 updates: forced past the convergence test
    assert dataclasses.replace(used, tag=0) == dataclasses.replace(estimate, tag=0) and result.generation == 2
    expected = estimate_to_params(NOMINAL, estimate)
    assert float32_equal(read_active_params(link).params, expected)
    assert read_active_params(link).params.focal_length_mm == float(np.float32(estimate.values[0]))


def test_accept_refuses_an_unconverged_estimate_unless_forced():
    sim = simulate(SimConfig(camera=CAMERA, frames=20, noise_px=0.05, seed=9))
    s = sensor(RecursiveEstimator(), session_frames(sim.session))
    link = LoopbackLink(s)
    assert len(stream_frames(link, 15).frames) == 15
    with pytest.raises(UserError, match="not converged: only 15 updates") as info:
        accept_estimate(link)
    assert "\n" not in str(info.value) and read_active_params(link).generation == 1
    assert accept_estimate(link, force=True)[0].generation == 2


def test_accept_commits_an_estimate_that_passes_the_convergence_test():
    """ACCEPT_MIN_UPDATES (300) updates of the seed-004 simulation: every sigma is under a quarter of its prior."""
    sim = simulate(SimConfig(camera=CAMERA, frames=ACCEPT_MIN_UPDATES + 10, noise_px=0.05, seed=9))
    s = sensor(RecursiveEstimator(), session_frames(sim.session))
    link = LoopbackLink(s)
    stream_frames(link, ACCEPT_MIN_UPDATES + 10, keep_frames=False)
    estimate = link.read_estimate()
    assert estimate.n_updates >= ACCEPT_MIN_UPDATES
    assert estimate_convergence(NOMINAL, estimate) is None
    result, _ = accept_estimate(link)
    assert result.generation == 2


def test_the_convergence_test_names_a_parameter_whose_sigma_is_too_large():
    estimate = m.Estimate(
        estimated_mask=0b111,
        n_updates=ACCEPT_MIN_UPDATES,
        values=(70.0, 511.5, 511.5, *[0.0] * 7),
        sigma=(0.01, 20.0, 0.5, *[math.nan] * 7),
    )
    why = estimate_convergence(NOMINAL, estimate)
    assert why.startswith("sigma of x0 is 20") and "0.25 of its prior (12.8)" in why  # prior: 5 % of 1024 px


def test_the_first_upload_to_a_sensor_with_blank_flash_commits_generation_one():
    blank = EmulatedSensor(Firmware(banks.erased_store()), iter(()))
    assert safe_upload(LoopbackLink(blank), CAMERA).generation == 1
    assert read_active_params(LoopbackLink(blank)).generation == 1
