"""Property-based tests (hypothesis) of every decoder: serial frames, every message, CAN frames and the stream
assembler, ISO-TP, Modbus blocks, the parameter table. For any input a decoder raises only its documented error class
(never an internal error), and a corrupted valid input is never accepted as something else.

The long run (10^6 inputs per decoder) is ``python scripts/fuzz.py``.
"""

import math

import can
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostlink.links.can_link import IsoTpChannel, StreamAssembler
from protocol import can_frames as cf
from protocol import messages as m
from protocol import modbus_map as mm
from protocol.framing import FramingError, decode_frame, encode_frame
from protocol.param_table import TABLE_BYTES, TableError, decode_table

#: Examples per property: enough to hit every message type and layout many times, fast enough for CI (each < 2 s).
EXAMPLES = 300
_settings = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])

type_bytes = st.sampled_from([s.type_id for s in m.MESSAGES])


def _message_bytes() -> st.SearchStrategy[bytes]:
    """Bytes that start with a real type byte and are about the size of its message (so decoding gets deep)."""
    return st.builds(lambda t, body: bytes([t]) + body, type_bytes, st.binary(max_size=120))


def _frame(draw_frame: int, n: int, seed: int) -> m.CentroidFrame:
    rng = np.random.default_rng(seed)
    return m.CentroidFrame(
        frame=draw_frame,
        t_us=1_773_454_200_000_000 + 100_000 * draw_frame,
        star_id=rng.integers(0, 1 << cf.STAR_ID_BITS, n).astype(np.uint32),
        x_px=np.round(rng.uniform(-512, 7000, n) * 1024) / 1024,
        y_px=np.round(rng.uniform(-512, 7000, n) * 1024) / 1024,
        mag=np.full(n, math.nan),
    )


# ------------------------------------------------------------------------------------------ messages
@_settings
@given(_message_bytes())
def test_any_bytes_decode_to_a_message_or_a_decode_error_and_an_accepted_one_is_canonical(data):
    try:
        msg = m.decode(data)
    except m.DecodeError:
        return
    again = m.encode(msg)
    if not any(f.fmt == "f" for f in m.spec_of(msg).fields):  # float32 NaN payloads may be quietened by Python
        assert again == data  # one message, one byte string: nothing else was accepted as it
    else:
        assert len(again) == len(data) and m.decode(again) == msg or _nan_equal(m.decode(again), msg)


def _nan_equal(a, b) -> bool:
    return all(
        x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
        for f in a.__dataclass_fields__
        for x, y in zip(np.atleast_1d(getattr(a, f)), np.atleast_1d(getattr(b, f)), strict=True)
    )


@_settings
@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_raise_anything_but_decode_error(data):
    try:
        m.decode(data)
    except m.DecodeError:
        pass


# ----------------------------------------------------------------------------------------- serial framing
@_settings
@given(st.integers(0, 65535), _message_bytes(), st.data())
def test_a_serial_frame_with_any_bit_flipped_is_refused(seq, payload, data):
    wire = encode_frame(seq, payload)[:-1]  # without the delimiter
    bit = data.draw(st.integers(0, 8 * len(wire) - 1))
    bad = bytearray(wire)
    bad[bit // 8] ^= 1 << (bit % 8)
    if 0 in bad:
        return  # a flip that makes a 0x00 splits the frame at the delimiter: the pieces are refused separately
    try:
        got = decode_frame(bytes(bad))
    except FramingError:
        return
    raise AssertionError(f"corrupted frame accepted: {got}")


@_settings
@given(st.binary(max_size=400))
def test_arbitrary_bytes_are_a_serial_frame_or_a_framing_error(data):
    try:
        decode_frame(data)
    except FramingError:
        pass


# ------------------------------------------------------------------------------------------------- CAN
@_settings
@given(st.sampled_from([cf.COMMAND.frame_id, cf.ACK.frame_id, cf.STAGE_FLOAT.frame_id, 0x7FF]), st.binary(max_size=9))
def test_any_single_frame_decodes_or_raises_can_decode_error(frame_id, data):
    try:
        cf.decode_single(frame_id, data)
    except cf.CanDecodeError:
        pass


stream_ids = st.sampled_from(sorted(m.frame_id for m in cf.CAN_MESSAGES if m.sender == cf.SENSOR))


@_settings
@given(st.lists(st.tuples(stream_ids, st.binary(min_size=0, max_size=9)), max_size=60))
def test_the_stream_assembler_takes_any_frame_sequence_without_an_internal_error(frames):
    asm = StreamAssembler()
    for fid, data in frames:
        asm.feed(fid, data)
    asm.finish()


@_settings
@given(st.integers(0, 2**31), st.integers(0, 12), st.integers(0, 2**32 - 1), st.data())
def test_a_can_stream_with_one_bit_flipped_never_delivers_a_wrong_frame(first, n_stars, seed, data):
    frames = [_frame(first + k, n_stars, seed + k) for k in range(3)]
    enc = cf.StreamEncoder()
    wire = [pair for f in frames for pair in enc.encode(f)]
    i = data.draw(st.integers(0, len(wire) - 1))
    bit = data.draw(st.integers(0, 8 * len(wire[i][1]) - 1))
    bad = bytearray(wire[i][1])
    bad[bit // 8] ^= 1 << (bit % 8)
    wire[i] = (wire[i][0], bytes(bad))
    asm = StreamAssembler()
    got = [out for fid, d in wire if isinstance(out := asm.feed(fid, d), m.CentroidFrame)]
    sent = {f.frame: f for f in frames}
    for f in got:
        assert f.same_as(sent[f.frame])  # every delivered frame is exactly a sent one
    assert len(got) + asm.lost <= len(frames)  # and the one it refused is counted (when a later one came)
    if wire[i][0] != cf.TIME_BASE.frame_id:  # a wrong time base spoils the frames until the next (at most 16)
        assert len(got) == len(frames) - 1  # any other flipped bit costs exactly the frame it is in


@_settings
@given(st.lists(st.binary(min_size=0, max_size=8), max_size=40))
def test_isotp_takes_any_frames_without_an_internal_error(payloads):
    sent = []
    chan = IsoTpChannel(sent.append, cf.ISOTP_HOST_TO_SENSOR_ID, cf.ISOTP_SENSOR_TO_HOST_ID)
    for p in payloads:
        chan.feed(can.Message(arbitration_id=cf.ISOTP_SENSOR_TO_HOST_ID, data=p, is_extended_id=False))
        for msg in chan.poll():  # whatever ISO-TP assembles is then a message or a DecodeError
            try:
                m.decode(msg)
            except m.DecodeError:
                pass


# ---------------------------------------------------------------------------------------------- Modbus
block_names = st.sampled_from([b.name for b in mm.load_map().checked_blocks])


@_settings
@given(block_names, st.integers(0, 255), st.integers(0, 2**32 - 1), st.data())
def test_a_modbus_block_with_any_bit_flipped_fails_its_check(name, n_stars, seed, data):
    regmap = mm.load_map()
    block = regmap.checked_block(name)
    image = [int(v) for v in np.random.default_rng(seed).integers(0, 1 << 16, regmap.table_size("input"))]
    if block.stars is not None:
        mm.put(image, block.stars, n_stars)
    mm.seal_block(block, image)
    lo, count = block.read_span(mm.block_n_stars(block, image, 0))
    words = image[lo : lo + count]
    assert mm.block_intact(block, words, lo)
    k = data.draw(st.integers(0, 16 * count - 1))
    words[k // 16] ^= 1 << (k % 16)
    assert not mm.block_intact(block, words, lo)


@_settings
@given(block_names, st.lists(st.integers(0, 65535), max_size=300))
def test_random_registers_never_raise_from_the_block_check(name, words):
    block = mm.load_map().checked_block(name)
    mm.block_intact(block, words, block.first.address)


# --------------------------------------------------------------------------------------- parameter table
@_settings
@given(st.binary(max_size=2 * TABLE_BYTES))
def test_any_bytes_are_a_parameter_table_or_a_table_error(data):
    try:
        values = decode_table(data)
    except TableError:
        assert len(data) != TABLE_BYTES
        return
    assert values.tobytes() == data  # bit for bit, NaN payloads included
