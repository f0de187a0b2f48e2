"""``hostlink import-can``: a recorded CAN capture turned back into a session (``hostlink.links.can_capture``)."""

from __future__ import annotations

import argparse

HELP = "turn a CAN capture (BLF, ASC, CSV... read by python-can) into a session CSV"
DESCRIPTION = (
    "Reads a CAN log recorded on a bus with a star sensor on it (any format python-can's LogReader reads: Vector "
    ".blf and .asc, python-can .csv, PEAK .trc, candump .log, SQLite .db), decodes the sensor's stream frames "
    "(TIME_BASE, FRAME_HEADER, STAR; docs/links.md) and writes SESSION.csv with the columns `hostlink stream` writes "
    "over CAN (frame, t_utc, star_id, x_px, y_px, mag; mag is empty: a STAR frame carries no magnitude). Frames "
    "whose stars did not all arrive are dropped and counted; other traffic on the bus is ignored."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG", help="the CAN capture (.blf, .asc, .csv, .trc, .log, .db ...)")
    parser.add_argument("--out", required=True, metavar="SESSION.csv", help="session file to write")
    parser.add_argument(
        "--channel",
        metavar="CH",
        help="only frames on this channel, as python-can reports it (needed when the stream is on several)",
    )


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.api import WIRE_PX_FORMAT, frames_to_session, read_can_capture, write_session

    capture = read_can_capture(args.log, channel=args.channel)
    write_session(args.out, frames_to_session(capture.frames), float_format=WIRE_PX_FORMAT)
    print(
        f"{args.out}: {len(capture.frames)} frames, {capture.n_stars} stars from {capture.stream_can_frames} stream "
        f"CAN frames of {capture.can_frames}; dropped {capture.incomplete} incomplete frame(s); "
        f"{capture.counter_gaps} frame(s) missing by the frame counter; {capture.corrupt} corrupt",
        file=sys.stderr,
    )
    return 0
