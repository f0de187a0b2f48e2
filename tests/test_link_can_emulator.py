"""The whole cycle on CAN against the emulator process (``hostlink emulate --transport can``): stream with loss
counting, safe upload read back equal to float32, a refused set with its reason, cantools decoding of the captured
stream with the DBC, a plain DBC tool driving an upload with single frames, and a dropped link as one line."""

import signal
import time
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink.errors import LinkError
from hostlink.files.params import save_params
from hostlink.links import open_link
from hostlink.links.base import CommandRefused
from hostlink.links.operations import float32_equal, read_active_params
from hostlink.sky.simulate import seed004_camera
from onboard.banks import params_to_table
from protocol import can_frames as cf
from protocol.crc import crc32
from protocol.messages import MsgType, NakCode
from protocol.param_table import PARAM_FIELDS

DBC = Path(__file__).resolve().parents[1] / "protocol" / "startracker.dbc"
BITRATE = "500000"


@pytest.fixture(scope="module")
def can_sensor():
    """One simulated-sky CAN emulator shared by the command tests (each test leaves a consistent sensor)."""
    with running_emulator("can", "--sim-frames", "40", "--bitrate", BITRATE) as info:
        yield info


def test_upload_reads_back_equal_to_float32(can_sensor, tmp_path):
    camera = seed004_camera()
    path = tmp_path / "camera.json"
    save_params(path, camera)
    run = hostlink("upload", str(path), "--link", can_sensor["link"])
    assert run.returncode == 0, run.stderr
    with open_link(can_sensor["link"]) as link:
        active = read_active_params(link)
    assert float32_equal(active.params, camera) and active.crc32 == crc32(params_to_table(camera))


def test_a_bad_set_is_refused_by_the_sensor_with_its_reason(can_sensor):
    camera = seed004_camera()
    table = bytearray(params_to_table(camera))
    table[8:12] = np.float32(1e6).tobytes()  # principal_point_x_px far off the detector
    with open_link(can_sensor["link"]) as link:
        before = link.read_active()
        link.stage_begin(len(table))
        link.stage_chunk(0, bytes(table))
        with pytest.raises(CommandRefused) as refused:
            link.stage_verify(crc32(bytes(table)))
        after = link.read_active()
    assert refused.value.code == NakCode.INVALID_PARAMS and "principal_point_px[0]" in refused.value.text
    assert len(str(refused.value).splitlines()) == 1
    assert (after.generation, after.crc32, after.table) == (before.generation, before.crc32, before.table)


def _decode_capture(db, captured):
    """Rebuild centroid frames from raw CAN frames with cantools alone (no project decoder)."""
    frames, t_base, current = [], None, None
    for msg in captured:
        if msg.arbitration_id not in (cf.TIME_BASE.frame_id, cf.FRAME_HEADER.frame_id, cf.STAR.frame_id):
            continue
        sig = db.decode_message(msg.arbitration_id, bytes(msg.data))
        if msg.arbitration_id == cf.TIME_BASE.frame_id:
            t_base = sig["t_base_us"]
        elif msg.arbitration_id == cf.FRAME_HEADER.frame_id and t_base is not None:
            current = {"frame": sig["frame"], "t_us": t_base + sig["t_offset_us"], "n": sig["n_stars"], "stars": []}
            frames.append(current)
        elif current is not None:
            current["stars"].append((sig["star_id"], sig["x_px"], sig["y_px"]))
    return [f for f in frames if len(f["stars"]) == f["n"]]


#: Seconds to wait for the sniffer to join the emulator's bus (its hub thread runs in another process, which a
#: loaded machine may delay); reaching it fails the test.
SNIFFER_JOIN_DEADLINE_S = 30.0
#: Seconds of quiet on the bus that mean nothing more is on its way.
QUIET_S = 0.3


def _sniffer_joined(sniffer, link) -> None:
    """Return once the listen-only ``sniffer`` sees the bus: status requests over ``link`` until their frames reach
    it, then the rest of them drained. Replaces a fixed sleep that raced the emulator process's hub."""
    deadline = time.monotonic() + SNIFFER_JOIN_DEADLINE_S
    while time.monotonic() < deadline:
        link.status()
        if sniffer.recv(QUIET_S) is not None:
            while sniffer.recv(QUIET_S) is not None:
                assert time.monotonic() < deadline, "the bus never went quiet (is the sensor streaming?)"
            return
    raise AssertionError(f"the sniffer saw nothing on the bus within {SNIFFER_JOIN_DEADLINE_S} s")


def test_cantools_decodes_the_streamed_frames_with_the_dbc(can_sensor):
    db = cantools.database.load_file(str(DBC))
    url = can_sensor["link"].split(":", 2)[2].rsplit("@", 1)[0]
    sniffer = can.Bus(interface="slcan", channel=url, sleep_after_open=0, listen_only=True)
    try:
        with open_link(can_sensor["link"]) as link:
            _sniffer_joined(sniffer, link)  # the hub delivers to the sniffer before the stream starts
            link.set_streaming(True)
            received = [link.recv_frame() for _ in range(8)]
            link.set_streaming(False)
        captured = []
        while (msg := sniffer.recv(0.3)) is not None:
            captured.append(msg)
    finally:
        sniffer.shutdown()
    decoded = {f["frame"]: f for f in _decode_capture(db, captured)}
    for frame in received:
        d = decoded[frame.frame]
        assert d["t_us"] == frame.t_us
        ids, xs, ys = (np.array(v) for v in zip(*d["stars"], strict=True)) if d["stars"] else ([], [], [])
        # cantools scales raw * 2^-10 - 512 in float64: exact on the grid, so equality is exact
        assert np.array_equal(ids, frame.star_id) and np.array_equal(xs, frame.x_px) and np.array_equal(ys, frame.y_px)


def test_a_plain_dbc_tool_uploads_with_single_frames(can_sensor):
    """No project code on the wire side: python-can + cantools + the DBC stage, verify and commit a set."""
    db = cantools.database.load_file(str(DBC))
    camera = seed004_camera()
    table = params_to_table(camera)
    values = np.frombuffer(table, dtype="<f4")
    url = can_sensor["link"].split(":", 2)[2].rsplit("@", 1)[0]
    bus = can.Bus(interface="slcan", channel=url, sleep_after_open=0)

    def send_and_ack(name, signals, tag):
        bus.send(
            can.Message(
                arbitration_id=db.get_message_by_name(name).frame_id,
                is_extended_id=False,
                data=db.encode_message(name, {"tag": tag, **signals}),
            )
        )
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            msg = bus.recv(0.5)
            if msg is not None and msg.arbitration_id == db.get_message_by_name("ACK").frame_id:
                ack = db.decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
                if ack["tag"] == tag:
                    return ack
        raise AssertionError(f"no ACK for {name} (a NAK comes by ISO-TP)")

    with open_link(can_sensor["link"]) as link:
        generation = link.status().active_generation
    try:
        time.sleep(0.05)
        nonce = send_and_ack("COMMAND", {"type": int(MsgType.STAGE_BEGIN), "length": len(table)}, 1)["value"]
        for i, _ in enumerate(PARAM_FIELDS):
            send_and_ack("STAGE_FLOAT", {"field": i, "reserved": 0, "value": float(values[i])}, 10 + i)
        crc = crc32(table)
        send_and_ack("COMMAND", {"type": int(MsgType.STAGE_VERIFY), "verify_crc32": crc}, 30)
        bind = db.encode_message("COMMIT_BIND", {"nonce": nonce, "expected_generation": generation})
        bus.send(
            can.Message(arbitration_id=db.get_message_by_name("COMMIT_BIND").frame_id, is_extended_id=False, data=bind)
        )
        ack = send_and_ack("COMMAND", {"type": int(MsgType.COMMIT), "commit_crc32": crc}, 31)
    finally:
        bus.shutdown()
    with open_link(can_sensor["link"]) as link:
        active = link.read_active()
    assert active.generation == ack["value"] and bytes(active.table) == table


def test_a_dropped_can_link_is_a_one_line_error():
    with running_emulator("can", "--sim-frames", "20", "--bitrate", BITRATE) as info:
        link = open_link(info["link"])
        link.status()
        info["process"].send_signal(signal.SIGKILL)
        info["process"].wait(10)
        with pytest.raises(LinkError) as lost:
            for _ in range(3):  # the reader notices the closed socket within one poll
                link.status()
        link.close()
    assert len(str(lost.value).splitlines()) == 1
    run = hostlink("params", "--link", info["link"])
    assert run.returncode == 3 and len(run.stderr.strip().splitlines()) == 1 and "CAN" in run.stderr
