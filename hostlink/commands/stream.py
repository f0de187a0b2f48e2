"""``hostlink stream``: record centroid frames from a sensor into a session file."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

HELP = "record N centroid frames from a sensor into a session file (CSV or Parquet)"
DESCRIPTION = (
    "Starts the sensor's centroid stream, records --frames frames with a progress bar, stops the stream and writes "
    "SESSION.csv (frame, t_utc, star_id, x_px, y_px, mag), or SESSION.parquet, frame by frame as they arrive (into "
    "a partial file .SESSION.csv.<random>.partial beside it, created exclusively and renamed at the end; after "
    "Ctrl-C or a dropped link the frames received are kept). Lost messages are counted from the stream's start "
    "(frames lost before the first one received included) and reported. Centroids arrive in fixed point (2^-10 px) "
    "and are written exactly."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument("--frames", type=int, required=True, metavar="N", help="frames to record")
    parser.add_argument(
        "--out",
        required=True,
        metavar="SESSION.csv",
        help="session file to write: CSV, or Parquet when the name ends in .parquet (columnar: exact float64, "
        "half the size, faster to read; docs/file-formats.md)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.api import StreamResult, progress_bar, record_session

    result = StreamResult()
    try:
        with open_link_from_args(args) as link, progress_bar("frames", args.frames, enabled=not args.quiet) as advance:
            record_session(link, args.frames, args.out, progress=advance, result=result)
    except KeyboardInterrupt:
        if not result.frames_received:
            raise
        print(
            f"hostlink stream: interrupted; the {result.frames_received} frames received before were written to "
            f"{args.out}",
            file=sys.stderr,
        )
        return 130
    note = f"; the sensor's stream ended after {result.frames_received} frames" if result.ended else ""
    print(
        f"{args.out}: {result.frames_received} frames, {result.n_stars} stars; lost {result.lost_messages} "
        f"message(s) since the stream's start, {result.corrupt_frames} corrupt{note}",
        file=sys.stderr,
    )
    return 0
