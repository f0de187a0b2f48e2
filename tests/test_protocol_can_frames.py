"""CAN frame layouts: the checked-in DBC is the generated one, cantools (an outside implementation of the DBC format)
decodes and encodes every single-frame message exactly as protocol.can_frames does, and the star fixed point
carries the protocol's 2^-10 px grid exactly."""

from pathlib import Path

import cantools
import numpy as np
import pytest

from protocol import can_frames as cf
from protocol.crc import crc16_ccitt, crc32
from protocol.messages import (
    Ack,
    CentroidFrame,
    Commit,
    EncodeError,
    GetStatus,
    MsgType,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    dequantise_px,
    quantise_px,
)
from protocol.param_table import PARAM_FIELDS

DBC_PATH = Path(__file__).resolve().parents[1] / "protocol" / "startracker.dbc"


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(str(DBC_PATH))


def test_checked_in_dbc_is_the_generated_one():
    # regenerate with: python -m protocol.can_frames > protocol/startracker.dbc
    assert DBC_PATH.read_text() == cf.dbc_text()


def test_dbc_describes_every_single_frame_message_with_float_signals_declared(db):
    assert {(m.frame_id, m.name) for m in db.messages} == {(m.frame_id, m.name) for m in cf.CAN_MESSAGES}
    for m in db.messages:
        assert not m.is_extended_frame and m.length == 8
    value = db.get_message_by_name("STAGE_FLOAT").get_signal_by_name("value")
    assert value.is_float and value.length == 32  # SIG_VALTYPE_ ... : 1 was read
    ids = [m.frame_id for m in cf.CAN_MESSAGES]
    assert cf.ISOTP_HOST_TO_SENSOR_ID not in ids and cf.ISOTP_SENSOR_TO_HOST_ID not in ids


def _random_frame(rng, n, frame=7):
    steps = rng.integers(-512 * 1024, 7680 * 1024, size=(2, n))  # the whole star range, on the 2^-10 grid
    return CentroidFrame(
        frame=frame,
        t_us=1_773_000_000_000_000,
        star_id=rng.integers(0, 131072, n).astype(np.uint32),
        x_px=dequantise_px(steps[0]),
        y_px=dequantise_px(steps[1]),
        mag=np.full(n, np.nan),
    )


def test_cantools_decodes_star_frames_to_the_same_centroids(db):
    rng = np.random.default_rng(1)
    frame = _random_frame(rng, 200, frame=13)
    payloads = cf.word_bytes(cf.encode_stars(frame))
    star = db.get_message_by_name("STAR")
    for i in range(frame.n_stars):
        sig = star.decode(payloads[8 * i : 8 * i + 8], scaling=True)
        # cantools computes raw * 2^-10 - 512 in float64: exact for 23-bit raws, so equality is exact
        assert sig["x_px"] == frame.x_px[i] and sig["y_px"] == frame.y_px[i]
        assert sig["star_id"] == frame.star_id[i] and sig["frame_parity"] == 1
    star_id, x, y, parity = cf.decode_stars(cf.payload_words(payloads))
    assert np.array_equal(x, frame.x_px) and np.array_equal(y, frame.y_px) and np.array_equal(star_id, frame.star_id)
    assert np.all(parity == 1)


def test_star_positions_travel_on_the_protocol_fixed_point_grid_exactly():
    rng = np.random.default_rng(2)
    x = rng.uniform(-0.5, 2047.5, 500)
    y = rng.uniform(-0.5, 2047.5, 500)
    frame = CentroidFrame(frame=0, t_us=0, star_id=np.zeros(500, np.uint32), x_px=x, y_px=y, mag=np.full(500, 5.0))
    _, gx, gy, _ = cf.decode_stars(cf.encode_stars(frame))
    # identical (bit for bit) to what the serial codec delivers: dequantise(quantise(x))
    assert np.array_equal(gx, dequantise_px(quantise_px(x))) and np.array_equal(gy, dequantise_px(quantise_px(y)))


@pytest.mark.parametrize("x_px, star_id", [(-512.001, 1), (7680.0, 1), (100.0, 131072)])
def test_a_star_outside_the_can_layout_is_refused(x_px, star_id):
    frame = CentroidFrame(
        frame=0,
        t_us=0,
        star_id=np.array([star_id], np.uint32),
        x_px=np.array([x_px]),
        y_px=np.array([10.0]),
        mag=np.array([np.nan]),
    )
    with pytest.raises(EncodeError):
        cf.encode_stars(frame)


def test_cantools_decodes_header_time_base_and_end_of_stream(db):
    header = db.decode_message(cf.FRAME_HEADER.frame_id, cf.encode_header(0xDEADBEEF, 17, (1 << 24) - 1))
    assert header == {"frame": 0xDEADBEEF, "n_stars": 17, "t_offset_us": (1 << 24) - 1}
    t_us = 1_773_454_299_123_456
    assert db.decode_message(cf.TIME_BASE.frame_id, cf.encode_time_base(t_us))["t_base_us"] == t_us
    assert cf.decode_time_base(cf.encode_time_base(-5)) == -5
    end = db.decode_message(cf.END_OF_STREAM.frame_id, cf.encode_end_of_stream(99, 7))
    payload = cf.encode_end_of_stream(99, 7)
    assert end == {"frames_sent": 99, "last_frame": 7, "check": crc16_ccitt(payload[0:2] + payload[4:8])}
    assert cf.decode_end_of_stream(payload) == (99, 7)
    assert cf.decode_header(cf.encode_header(5, 0, 1234)) == (5, 0, 1234)


def test_time_base_is_needed_exactly_when_the_offset_does_not_fit():
    assert cf.needs_time_base(10, None)
    assert not cf.needs_time_base(10, 10) and not cf.needs_time_base(10 + (1 << 24) - 1, 10)
    assert cf.needs_time_base(10 + (1 << 24), 10) and cf.needs_time_base(9, 10)


COMMANDS = [
    GetStatus(tag=1),
    StreamControl(tag=2, enable=True),
    StreamControl(tag=3, enable=False),
    StageBegin(tag=4, length=52),
    StageVerify(tag=5, crc32=0xCBF43926),
    ReadStaged(tag=6),
    Commit(tag=7, crc32=0xFFFFFFFF),
    ReadActive(tag=8),
    ReadEstimate(tag=65535),
]


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: type(c).__name__ + str(c.tag))
def test_short_commands_round_trip_and_cantools_reads_them(db, cmd):
    fid, data = cf.encode_single(cmd)
    assert fid == cf.COMMAND.frame_id and len(data) == 8
    assert cf.decode_single(fid, data) == cmd
    decoded = db.decode_message(fid, data, decode_choices=False)
    assert decoded["type"] == int(cmd.TYPE) and decoded["tag"] == cmd.tag
    arg = {
        "StreamControl": "enable",
        "StageBegin": "length",
        "StageVerify": "verify_crc32",
        "Commit": "commit_crc32",
    }.get(type(cmd).__name__)
    if arg:
        assert decoded[arg] == int(
            getattr(cmd, "enable" if arg == "enable" else "length" if arg == "length" else "crc32")
        )


def test_a_dbc_tool_can_build_commands_and_read_acks(db):
    data = db.encode_message("COMMAND", {"type": int(MsgType.COMMIT), "tag": 42, "commit_crc32": 0x12345678})
    assert cf.decode_single(cf.COMMAND.frame_id, data) == Commit(tag=42, crc32=0x12345678)
    fid, ack = cf.encode_single(Ack(tag=42, command=int(MsgType.COMMIT), value=3))
    assert db.decode_message(fid, ack, decode_choices=False) == {"type": 0x80, "tag": 42, "command": 7, "value": 3}


def test_stage_float_is_a_four_byte_stage_chunk_of_the_float32_value(db):
    value = 0.1  # not representable: the frame carries float32(0.1), the table's rounding
    data = db.encode_message("STAGE_FLOAT", {"tag": 9, "field": 2, "reserved": 0, "value": value})
    chunk = cf.decode_single(cf.STAGE_FLOAT.frame_id, data)
    assert chunk == StageChunk(tag=9, offset=8, data=np.float32(value).tobytes())
    assert cf.encode_stage_float(9, 2, value) == data
    assert db.decode_message("STAGE_FLOAT", data)["field"] == PARAM_FIELDS[2]


def test_malformed_single_frames_are_refused():
    with pytest.raises(cf.CanDecodeError):
        cf.decode_single(cf.COMMAND.frame_id, bytes([0x04]) + bytes(7))  # STAGE_CHUNK is not a short command
    with pytest.raises(cf.CanDecodeError):
        cf.decode_single(cf.COMMAND.frame_id, bytes(5))
    with pytest.raises(cf.CanDecodeError):
        beyond = len(cf.PARAM_FIELDS)  # one past the last table field
        cf.decode_single(cf.STAGE_FLOAT.frame_id, cf.word_bytes(cf.pack(cf.STAGE_FLOAT, {"field": beyond})))
    with pytest.raises(EncodeError):
        cf.encode_single(StageChunk())


def test_worst_case_frame_lengths_match_the_published_values():
    # Davis, Burns, Bril & Lukkien (2007), "CAN schedulability analysis: refuted, revisited and revised", eq. 1:
    # C = (g + 8s + 13 + floor((g + 8s - 1) / 4)) bit times, g = 34 (11-bit id) or 54 (29-bit id);
    # the paper quotes 135 bits for 8 data bytes with 11-bit ids and 160 with 29-bit ids; 0 bytes give 55 / 80.
    assert cf.frame_bits_worst_case(8, False) == 135 and cf.frame_bits_worst_case(8, True) == 160
    assert cf.frame_bits_worst_case(0, False) == 55 and cf.frame_bits_worst_case(0, True) == 80


def _stream_frame(n_stars: int = 5, frame: int = 41) -> CentroidFrame:
    rng = np.random.default_rng(frame)
    return CentroidFrame(
        frame=frame,
        t_us=1_773_454_299_000_000 + frame * 100_000,
        star_id=rng.integers(1, 100_000, n_stars).astype(np.uint32),
        x_px=np.round(rng.uniform(0, 2048, n_stars) * 1024) / 1024,
        y_px=np.round(rng.uniform(0, 2048, n_stars) * 1024) / 1024,
        mag=np.full(n_stars, np.nan),
    )


def test_a_stream_frame_is_closed_by_a_frame_end_whose_crc_covers_time_header_and_stars(db):
    frames, t_base = cf.encode_stream_frame(_stream_frame(), None)
    ids = [fid for fid, _ in frames]
    assert ids == [cf.TIME_BASE.frame_id, cf.FRAME_HEADER.frame_id] + [cf.STAR.frame_id] * 5 + [cf.FRAME_END.frame_id]
    frame, crc = cf.decode_frame_end(frames[-1][1])
    stars = b"".join(d for fid, d in frames if fid == cf.STAR.frame_id)
    assert frame == 41 and crc == crc32(t_base.to_bytes(8, "little", signed=True) + frames[1][1] + stars)
    assert db.decode_message(cf.FRAME_END.frame_id, frames[-1][1]) == {"frame_crc32": crc, "frame": 41}


def test_end_of_stream_with_a_flipped_bit_is_refused():
    payload = bytearray(cf.encode_end_of_stream(1234, 99))
    for bit in range(64):
        bad = bytearray(payload)
        bad[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(cf.CanDecodeError):
            cf.decode_end_of_stream(bytes(bad))


def test_the_sensor_repeats_the_time_base_every_sixteen_frames():
    enc = cf.StreamEncoder()
    with_base = [k for k in range(40) if enc.encode(_stream_frame(2, k))[0][0] == cf.TIME_BASE.frame_id]
    assert with_base == [0, cf.TIME_BASE_EVERY_FRAMES, 2 * cf.TIME_BASE_EVERY_FRAMES]
