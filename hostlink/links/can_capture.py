"""A recorded CAN capture turned back into centroid frames (``hostlink import-can``).

Any log python-can reads (``can.LogReader``: Vector BLF ``.blf`` and ASC ``.asc``, python-can ``.csv``, PEAK ``.trc``,
candump ``.log``, SQLite ``.db``...) of a bus with a star sensor on it: its stream frames (TIME_BASE, FRAME_HEADER,
STAR, FRAME_END, END_OF_STREAM; ``protocol.can_frames``) are decoded by the same
:class:`~hostlink.links.can_link.StreamAssembler` as a live :class:`~hostlink.links.can_link.CanLink`, so an imported
capture gives exactly the frames ``hostlink stream`` would have recorded from the same bus. Everything else on the bus
(commands, ACKs, ISO-TP, other nodes' identifiers, extended, remote and error frames) is skipped.

A frame is taken only when its FRAME_END matches (frame counter and CRC-32 over time, header and stars). A frame
whose header arrived but not all of its stars or not its FRAME_END is dropped and counted (``incomplete``), as are
frames missing from the frame counter without a trace (``counter_gaps``: lost on the bus, or exposures made while
the stream was off) and CAN frames or whole frames that fail their checks (``corrupt``). Times come from the
TIME_BASE frames, never from the log's timestamps. A capture whose frame counter goes backwards (the sensor
restarted) or that holds stream frames on more than one channel cannot be one session: refused with a one-line
:class:`UserError`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can

from hostlink.errors import UserError, one_line
from hostlink.links.can_link import STREAM_FRAME_IDS, StreamAssembler
from protocol.messages import CentroidFrame, EndOfStream


@dataclass
class CaptureImport:
    """The centroid frames of a capture and what was dropped on the way."""

    frames: list[CentroidFrame] = field(default_factory=list)
    #: CAN frames read from the log, and of those the star-sensor stream frames
    can_frames: int = 0
    stream_can_frames: int = 0
    #: frames dropped because some of their STAR frames are missing (header seen, stars not all in the capture)
    incomplete: int = 0
    #: frames missing by the frame counter (lost on the bus, or made while the stream was off)
    counter_gaps: int = 0
    #: stream CAN frames that are not valid (a star without a header, wrong frame parity, no time base yet...)
    corrupt: int = 0
    #: END_OF_STREAM frames seen (the sensor's frame source ended)
    ends: int = 0
    channel: object = None

    @property
    def n_stars(self) -> int:
        return sum(f.n_stars for f in self.frames)


#: A Vector BLF file starts with this signature (python-can's can.io.blf reads the same file header).
BLF_SIGNATURE = b"LOGG"


def _check_blf_signature(path: Path) -> None:
    """A ``.blf`` file that is empty or does not start with :data:`BLF_SIGNATURE` is a one-line UserError saying so
    (python-can's own message would be a struct's "unpack requires a buffer of 72 bytes")."""
    try:
        with path.open("rb") as fh:
            head = fh.read(len(BLF_SIGNATURE))
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    if not head:
        raise UserError(f"{path}: empty file, not a BLF log (a BLF log starts with the signature LOGG)")
    if head != BLF_SIGNATURE:
        raise UserError(
            f"{path}: not a BLF log (it does not start with the signature LOGG; a text log needs its own suffix: "
            ".asc, .trc, .csv, .log)"
        )


def _messages(path: Path) -> Iterator[can.Message]:
    """The messages of a python-can log; any failure to read it is a one-line UserError."""
    if path.is_dir():
        raise UserError(f"{path}: is a directory, not a CAN log file (give one capture file: .blf, .asc, .trc ...)")
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    if path.suffix.lower() == ".blf":
        _check_blf_signature(path)
    count = 0
    try:
        with can.LogReader(str(path)) as reader:
            for msg in reader:
                count += 1
                yield msg
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - a third-party parser on a user's file: one line, never a traceback
        raise UserError(
            f"{path}: not a CAN log python-can reads (.blf, .asc, .csv, .trc, .log, .db ...): "
            f"{one_line(exc)} after {count} frames"
        ) from None


def read_can_capture(path: str | Path, channel: str | None = None) -> CaptureImport:
    """Decode the star-sensor stream of the capture at ``path``. ``channel``: only frames on this channel (as
    python-can's reader reports it, compared as text); required when the stream appears on several channels."""
    path = Path(path)
    result = CaptureImport()
    assembler = StreamAssembler()
    for msg in _messages(path):
        result.can_frames += 1
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            continue
        if msg.arbitration_id not in STREAM_FRAME_IDS:
            continue
        if channel is not None and str(msg.channel) != channel:
            continue
        if result.stream_can_frames == 0:
            result.channel = msg.channel
        elif msg.channel != result.channel:
            raise UserError(
                f"{path}: star-sensor frames on channels {result.channel} and {msg.channel}; choose one with --channel"
            )
        result.stream_can_frames += 1
        out = assembler.feed(msg.arbitration_id, bytes(msg.data))
        if isinstance(out, CentroidFrame):
            if result.frames and out.frame <= result.frames[-1].frame:
                raise UserError(
                    f"{path}: the frame counter goes back from {result.frames[-1].frame} to {out.frame} (the sensor "
                    f"restarted?); a session needs increasing frame numbers: split the capture there"
                )
            result.frames.append(out)
        elif isinstance(out, EndOfStream):
            result.ends += 1
    assembler.finish()
    result.incomplete = assembler.incomplete
    result.counter_gaps = assembler.lost - assembler.refused_between
    result.corrupt = assembler.corrupt
    if not result.frames:
        where = f" on channel {channel}" if channel is not None else ""
        raise UserError(
            f"{path}: no complete star-sensor frame{where} in {result.can_frames} CAN frames "
            f"({result.stream_can_frames} stream frames, {result.incomplete} incomplete, {result.corrupt} corrupt)"
        )
    return result
