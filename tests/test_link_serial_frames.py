"""The serial link's receive path (pyserial loop:// port, no sensor): losses are counted from sequence gaps,
corrupt frames are counted and skipped, and late replies never answer a newer command."""

import numpy as np
import pytest

from hostlink.errors import LinkError
from hostlink.links import open_link, split_link_string
from hostlink.links.serial_link import parse_target
from protocol import messages as m
from protocol.framing import encode_frame


def frame(k):
    return m.CentroidFrame(
        frame=k,
        t_us=1_000_000 * k,
        star_id=np.array([k + 1], np.uint32),
        x_px=np.array([k + 0.5]),
        y_px=np.array([2.25]),
        mag=np.array([3.0]),
    )


def test_link_strings_are_parsed_once():
    assert split_link_string("serial:/dev/ttyUSB0@115200") == ("serial", "/dev/ttyUSB0@115200")
    assert parse_target("/dev/ttyUSB0@115200") == ("/dev/ttyUSB0", 115200)
    assert parse_target("rfc2217://host:4000") == ("rfc2217://host:4000", 921600)


def test_gaps_and_corruption_are_counted_and_frames_still_arrive():
    link = open_link("serial:loop://", timeout_s=0.5)
    port = link._port  # loop:// reads back what is written: play the sensor's side
    wire = [encode_frame(seq, m.encode(frame(seq))) for seq in range(10)]
    corrupt = bytearray(wire[4])
    k = next(i for i in range(6, len(corrupt)) if corrupt[i] not in (0x00, 0x01))  # flip a bit, make no zero
    corrupt[k] ^= 0x01
    port.write(b"".join([wire[0], wire[1], wire[3], bytes(corrupt), wire[5], wire[9]]))
    got = [link.recv_frame().frame for _ in range(4)]
    assert got == [0, 1, 3, 5]
    assert link.recv_frame().frame == 9
    assert link.stats.corrupt_frames == 1
    assert link.stats.lost_messages == 1 + 1 + 3  # seq 2, seq 4 (corrupt), seq 6..8
    with pytest.raises(LinkError, match="no centroid frame within 0.1 s"):
        link.recv_frame(0.1)
    link.close()


def test_loss_is_counted_up_to_the_frame_delivered_not_to_what_was_read_beyond_it():
    """Frames 0, 1 and 5 arrive in one read (a busy host reads in large batches): when the caller has frame 1, no
    frame is lost yet; the three before frame 5 count when it is delivered. The loss the caller sees at a frame must
    not depend on how far the link has read ahead."""
    link = open_link("serial:loop://", timeout_s=0.5)
    link._port.write(b"".join(encode_frame(seq, m.encode(frame(seq))) for seq in (0, 1, 5)))
    seen = [(link.recv_frame().frame, link.stats.lost_messages) for _ in range(3)]
    assert seen == [(0, 0), (1, 0), (5, 3)]
    link.close()


def test_a_reply_lost_mid_stream_is_not_counted_as_a_lost_frame():
    """Stream messages are numbered apart from replies: a reply lost on the line between two consecutive frames
    (the host times out and resends) leaves no gap in the stream's numbers; a reply that arrives counts nothing."""
    link = open_link("serial:loop://", timeout_s=0.5)
    ack = m.Ack(tag=7, command=int(m.MsgType.READ_ESTIMATE), value=0)
    wire = [encode_frame(0, m.encode(frame(0))), encode_frame(40, m.encode(ack)), encode_frame(1, m.encode(frame(1)))]
    wire.append(encode_frame(2, m.encode(frame(2))))  # between 1 and 2 the reply numbered 41 is lost: not on the wire
    link._port.write(b"".join(wire))
    assert [link.recv_frame().frame for _ in range(3)] == [0, 1, 2]
    assert link.stats.lost_messages == 0
    link.close()


def test_end_of_stream_ends_recv_frame():
    link = open_link("serial:loop://", timeout_s=0.5)
    link._port.write(encode_frame(0, m.encode(frame(0))) + encode_frame(1, m.encode(m.EndOfStream(frames_sent=1))))
    assert link.recv_frame().frame == 0
    assert link.recv_frame() is None and link.recv_frame() is None
    link.close()
