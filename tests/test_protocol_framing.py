"""Serial framing: COBS with a CRC-32 and a sequence number per frame; corruption is detected, never passed on."""

import numpy as np
import pytest

from protocol.framing import (
    FrameSplitter,
    FramingError,
    decode_frame,
    encode_frame,
    framed_size,
    seq_gap,
)


@pytest.mark.parametrize("n", [0, 1, 100, 253, 254, 255, 600, 3600])
def test_frames_round_trip_and_contain_no_zero_but_the_delimiter(n):
    payload = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    wire = encode_frame(65535 + 3, payload)
    assert wire.endswith(b"\x00") and b"\x00" not in wire[:-1]
    assert len(wire) <= framed_size(n)
    frame = decode_frame(wire[:-1])
    assert frame.seq == 2 and frame.payload == payload


def test_every_single_byte_corruption_is_detected():
    wire = encode_frame(7, bytes(range(1, 60)))[:-1]
    for k in range(len(wire)):
        for flip in (0x01, 0x80, 0xFF):
            bad = bytearray(wire)
            bad[k] ^= flip
            if 0 in bad:
                continue  # a zero would split the frame on the wire; the splitter handles that case
            with pytest.raises(FramingError):
                decode_frame(bytes(bad))


def test_splitter_resynchronises_after_garbage():
    frames = [encode_frame(k, f"message {k}".encode()) for k in range(5)]
    stream = b"\x13\x37garbage\x00" + frames[0] + frames[1][:5] + b"\x00" + frames[2] + frames[3] + frames[4]
    split = FrameSplitter()
    got = []
    for i in range(0, len(stream), 7):  # arbitrary read sizes
        got += split.feed(stream[i : i + 7])
    decoded = []
    for raw in got:
        try:
            decoded.append(decode_frame(raw).seq)
        except FramingError:
            pass
    assert decoded == [0, 2, 3, 4]


def test_sequence_gaps_count_lost_frames_across_the_wrap():
    assert seq_gap(5, 6) == 0
    assert seq_gap(5, 9) == 3
    assert seq_gap(65534, 1) == 2


def test_splitter_discards_a_line_without_delimiters():
    split = FrameSplitter(max_frame_bytes=100)
    assert split.feed(b"\x01" * 150) == []
    assert split.discarded_bytes == 150
    assert [decode_frame(f).payload for f in split.feed(encode_frame(0, b"ok"))] == [b"ok"]
