"""The whole cycle on Modbus (TCP, and RTU framing over TCP) against the emulator process: stream with loss counting,
safe upload read back equal to float32, a refused set with its reason, link strings, and a dropped link as one
line."""

import signal

import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.errors import LinkError, UserError
from hostlink.files.params import save_params
from hostlink.links import open_link
from hostlink.links.base import CommandRefused
from hostlink.links.modbus_link import parse_target
from hostlink.links.operations import float32_equal, read_active_params
from hostlink.sky.simulate import seed004_camera
from onboard.banks import params_to_table
from protocol.crc import crc32
from protocol.messages import NakCode

LINKS = ["link", "link_rtu"]


@pytest.fixture(scope="module")
def modbus_sensor():
    with running_emulator("modbus", "--sim-frames", "40") as info:
        yield info


def test_a_release_that_did_not_take_delivers_no_frame_twice_and_counts_no_loss(replay_file):
    """Modbus TCP has no checksum: a release whose value was corrupted on the way up is answered like a good one, and
    the sensor keeps the window. Modelled here by writing every 3rd release with a wrong sequence number (the sensor
    releases only the window's own): the host must see the same window again, release it again, and neither deliver
    the frame twice nor count 2**32 - 1 lost (it did both in a 2,000-frame run with faults in both directions)."""
    from hostlink.links.operations import stream_frames

    with running_emulator("modbus", "--replay", str(replay_file)) as info:
        with open_link(info["link"]) as link:
            release, calls = link._release, [0]

            def unreliable_release(seq):
                calls[0] += 1
                release(seq + 1 if calls[0] % 3 == 0 else seq)  # answered OK, but releases nothing

            link._release = unreliable_release
            result = stream_frames(link, None, frame_timeout_s=20.0)
            lost, repeats = link.stats.lost_messages, link.stats.corrupt_frames
    frames = [f.frame for f in result.frames]
    assert result.ended and len(frames) == 50 and len(set(frames)) == 50  # every frame once
    assert lost == 0 and repeats >= 10  # ~1/3 of the releases did not take and were made again


@pytest.mark.parametrize("which", LINKS)
def test_upload_reads_back_equal_to_float32(modbus_sensor, tmp_path, which):
    camera = seed004_camera()
    path = tmp_path / "camera.json"
    save_params(path, camera)
    run = hostlink("upload", str(path), "--link", modbus_sensor[which])
    assert run.returncode == 0, run.stderr
    with open_link(modbus_sensor[which]) as link:
        active = read_active_params(link)
    assert float32_equal(active.params, camera) and active.crc32 == crc32(params_to_table(camera))


def test_unaligned_chunks_are_merged_in_the_staging_mailbox(modbus_sensor):
    table = params_to_table(seed004_camera())
    with open_link(modbus_sensor["link"]) as link:
        link.stage_begin(len(table))
        for offset in range(0, len(table), 7):  # 7-byte pieces split float32 values
            link.stage_chunk(offset, table[offset : offset + 7])
        link.stage_verify(crc32(table))
        assert bytes(link.read_staged().table) == table


@pytest.mark.parametrize("which", LINKS)
def test_a_bad_set_is_refused_by_the_sensor_with_its_reason(modbus_sensor, which):
    table = bytearray(params_to_table(seed004_camera()))
    table[8:12] = np.float32(1e6).tobytes()  # principal_point_x_px far off the detector
    with open_link(modbus_sensor[which]) as link:
        before = link.read_active()
        nonce = link.stage_begin(len(table))
        link.stage_chunk(0, bytes(table))
        with pytest.raises(CommandRefused) as refused:
            link.stage_verify(crc32(bytes(table)))
        with pytest.raises(CommandRefused) as not_verified:  # in its session, but never verified
            link.commit(crc32(bytes(table)), nonce=nonce, expected_generation=before.generation)
        after = link.read_active()
    assert refused.value.code == NakCode.INVALID_PARAMS and "principal_point_px[0]" in refused.value.text
    assert not_verified.value.code == NakCode.NOT_VERIFIED
    assert (after.generation, after.crc32, after.table) == (before.generation, before.crc32, before.table)


def test_modbus_link_strings():
    assert parse_target("modbus-tcp", "127.0.0.1:5020") == {
        "unit": 1,
        "host": "127.0.0.1",
        "port": 5020,
        "framing": "tcp",
    }
    assert parse_target("modbus-rtu", "tcp://10.0.0.5:4001,unit=7")["framing"] == "rtu"
    assert parse_target("modbus-rtu", "/dev/ttyUSB0@9600,parity=N") == {
        "unit": 1,
        "parity": "N",
        "serial_port": "/dev/ttyUSB0",
        "baud": 9600,
        "framing": "rtu",
    }
    for scheme, bad in (
        ("modbus-tcp", "127.0.0.1"),
        ("modbus-tcp", "h:99999"),
        ("modbus-tcp", "h:502,unit=300"),
        ("modbus-tcp", "h:502,parity=E"),
    ):
        with pytest.raises(UserError):
            parse_target(scheme, bad)


def test_a_dropped_modbus_link_is_a_one_line_error():
    with running_emulator("modbus", "--sim-frames", "20") as info:
        link = open_link(info["link"])
        link.status()
        info["process"].send_signal(signal.SIGKILL)
        info["process"].wait(10)
        with pytest.raises(LinkError) as lost:
            link.status()
        link.close()
    assert len(str(lost.value).splitlines()) == 1
    run = hostlink("stream", "--link", info["link"], "--frames", "5", "--out", "/dev/null")
    assert run.returncode == 3 and len(run.stderr.strip().splitlines()) == 1, run.stderr
