"""Protocol messages: every message round-trips through its codec, malformed bytes are refused cleanly, and the
fixed-point centroid resolution adds no measurable error at 0.01 px noise."""

import math

import numpy as np
import pytest

from onboard.params import ESTIMATE_NAMES
from protocol import messages as m
from protocol.crc import crc16_ccitt, crc32
from protocol.param_table import (
    PARAM_FIELDS,
    TABLE_BYTES,
    TableError,
    decode_table,
    encode_table,
    table_crc,
    table_from_mapping,
    table_to_mapping,
)

EXAMPLES = [
    m.GetStatus(tag=1),
    m.StreamControl(tag=2, enable=True),
    m.StreamControl(tag=3, enable=False),
    m.StageBegin(tag=4, length=TABLE_BYTES),
    m.StageChunk(tag=5, offset=32, data=bytes(range(20))),
    m.StageVerify(tag=6, crc32=0xDEADBEEF),
    m.ReadStaged(tag=7),
    m.Commit(tag=8, crc32=0x01020304),
    m.ReadActive(tag=9),
    m.ReadEstimate(tag=10),
    m.Ack(tag=11, command=m.MsgType.COMMIT, value=42),
    m.Nak(tag=12, command=m.MsgType.STAGE_VERIFY, code=m.NakCode.INVALID_PARAMS, text="focal_length_mm: must be > 0"),
    m.Telemetry(
        tag=13,
        streaming=True,
        stage_state=2,
        active_generation=7,
        active_crc32=0xFFFFFFFF,
        frames_processed=10,
        last_frame=9,
        estimator_updates=8,
    ),
    m.ParamTable(tag=14, bank=m.TableBank.STAGED, generation=0, crc32=5, table=bytes(range(TABLE_BYTES))),
    m.Estimate(
        tag=15,
        status=1,
        estimated_mask=0x3FF,
        base_generation=2,
        n_updates=100,
        last_frame=99,
        values=tuple(float(np.float32(v)) for v in np.linspace(1, 10, 10)),
        sigma=(0.5,) * 10,
    ),
    m.EndOfStream(frames_sent=123),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda x: type(x).__name__)
def test_every_message_round_trips_through_its_bytes(msg):
    data = m.encode(msg)
    assert data[0] == msg.TYPE
    assert m.decode(data) == msg


def test_every_message_type_has_an_example():
    covered = {type(x).TYPE for x in EXAMPLES} | {m.MsgType.CENTROID_FRAME}
    assert covered == set(m.MsgType)


def test_centroid_frame_round_trip_is_exact_on_the_fixed_point_grid():
    rng = np.random.default_rng(1)
    n = 40
    frame = m.CentroidFrame(
        frame=123456,
        t_us=1_773_454_200_123_456,
        star_id=rng.integers(1, 120_000, n).astype(np.uint32),
        x_px=np.round(rng.uniform(-0.5, 4095.5, n) * 1024) / 1024,
        y_px=np.round(rng.uniform(-0.5, 4095.5, n) * 1024) / 1024,
        mag=np.where(np.arange(n) % 7 == 0, np.nan, np.round(rng.uniform(-1.5, 9.0, n), 3)),
    )
    data = m.encode(frame)
    assert len(data) == m.frame_message_bytes(n) == 15 + 14 * n
    back = m.decode(data)
    assert back.same_as(frame)
    assert m.encode(back) == data


def test_quantisation_error_is_half_a_step_at_most():
    x = np.random.default_rng(2).uniform(-0.5, 8191.5, 100_000)
    err = m.dequantise_px(m.quantise_px(x)) - x
    assert np.max(np.abs(err)) <= m.CENTROID_LSB_PX / 2


def test_fixed_point_adds_no_measurable_error_at_one_hundredth_pixel_noise():
    rng = np.random.default_rng(3)
    truth = rng.uniform(0, 1024, 1_000_000)
    noisy = truth + rng.normal(0, 0.01, truth.size)
    wire = m.dequantise_px(m.quantise_px(noisy))
    q_err = wire - noisy
    # uniform rounding error: sigma = LSB / sqrt(12); 2 % covers the sampling error of 1e6 draws (0.07 %) many times
    assert np.std(q_err) == pytest.approx(m.CENTROID_LSB_PX / math.sqrt(12), rel=0.02)
    sigma_noise = np.std(noisy - truth)
    sigma_wire = np.std(wire - truth)
    inflation = sigma_wire / sigma_noise - 1
    # theory: sqrt(1 + (2.8e-4 / 0.01)^2) - 1 = 4.0e-4; a 1000-frame x 20-star session measures a noise sigma only
    # to 1/sqrt(2 * 20000) = 0.5 %, so anything below 1e-3 is not measurable
    assert 0 <= inflation < 1e-3


def test_magnitudes_travel_in_millimagnitudes_and_absent_stays_absent():
    mag = np.array([5.1, -1.46, 32.767, np.nan])
    back = m.dequantise_mag(m.quantise_mag(mag))
    assert np.array_equal(back, mag, equal_nan=True)  # exact: a file's 3 decimals survive
    with pytest.raises(m.EncodeError):
        m.quantise_mag(np.array([40.0]))


def test_unrepresentable_frames_are_refused_when_encoding():
    with pytest.raises(m.EncodeError):
        m.encode(
            m.CentroidFrame(
                frame=1,
                t_us=0,
                star_id=np.array([1], np.uint32),
                x_px=np.array([np.nan]),
                y_px=np.array([1.0]),
                mag=np.array([1.0]),
            )
        )
    n = m.MAX_STARS + 1
    with pytest.raises(m.EncodeError):
        m.encode(
            m.CentroidFrame(
                frame=1, t_us=0, star_id=np.ones(n, np.uint32), x_px=np.zeros(n), y_px=np.zeros(n), mag=np.zeros(n)
            )
        )
    with pytest.raises(m.EncodeError):
        m.encode(
            m.CentroidFrame(
                frame=1, t_us=0, star_id=np.ones(1, np.uint32), x_px=np.array([3e6]), y_px=np.zeros(1), mag=np.zeros(1)
            )
        )


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\x7f",
        bytes([m.MsgType.ACK]),
        bytes([m.MsgType.ACK]) + bytes(10),
        m.encode(m.StageChunk(tag=1, offset=0, data=b"abc"))[:-1],
        m.encode(EXAMPLES[-4])[:-1],
    ],
    ids=["empty", "unknown-type", "truncated-ack", "long-ack", "short-chunk", "short-table"],
)
def test_malformed_bytes_raise_decode_error(data):
    with pytest.raises(m.DecodeError):
        m.decode(data)


def test_random_bytes_never_raise_anything_but_decode_error():
    rng = np.random.default_rng(4)
    types = [t.value for t in m.MsgType]
    for _ in range(3000):
        n = int(rng.integers(0, 80))
        data = bytes([int(rng.choice(types))]) + rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        try:
            m.decode(data)
        except m.DecodeError:
            pass


def test_nak_text_is_cut_at_a_character_boundary():
    text = "é" * 100  # 200 bytes of UTF-8
    back = m.decode(m.encode(m.Nak(tag=1, command=1, code=1, text=text)))
    assert back.text == "é" * (m.NAK_TEXT_MAX // 2)


def test_estimate_field_order_is_the_onboard_one():
    assert m.ESTIMATE_FIELDS == ESTIMATE_NAMES


def test_crc_check_values_match_the_published_catalogue():
    # "check" values of CRC-32/ISO-HDLC and CRC-16/IBM-3740 (CCITT-FALSE) in the CRC RevEng catalogue
    assert crc32(b"123456789") == 0xCBF43926
    assert crc16_ccitt(b"123456789") == 0x29B1


def test_parameter_table_is_camera_fields_then_sigmas_as_little_endian_float32():
    values = [
        70.2262,
        12.0,
        500.0,
        530.0,
        1024,
        1024,
        -2e-10,
        3.5e-15,
        1e-21,
        1e-7,
        -1e-7,
        2e-8,
        -2e-8,
        7e-4,
        1.3,
        1.29,
        1.4e-10,
        5.8e-16,
        7.4e-22,
        2.2e-8,
        2.1e-8,
        2e-8,
        2e-8,
    ]
    data = encode_table(values)
    # 13 camera fields then 10 sigmas (ESTIMATE_NAMES order)
    assert len(data) == TABLE_BYTES == 92 == 4 * len(PARAM_FIELDS)
    assert PARAM_FIELDS[13] == "sigma_focal_length_mm" and PARAM_FIELDS[-1] == "sigma_s2"
    assert data[:4] == np.float32(70.2262).tobytes() and np.dtype("<f4").byteorder in "<="
    assert np.array_equal(decode_table(data), np.array(values, dtype=np.float32))
    assert table_crc(data) == crc32(data)
    assert table_from_mapping(table_to_mapping(data)) == data
    with pytest.raises(TableError):
        decode_table(data[:-1])
