"""``hostlink stream``: record centroid frames from a sensor into a session file."""

from __future__ import annotations

import argparse

from hostlink.linkopts import add_link_arguments, open_link_from_args

HELP = "record N centroid frames from a sensor into a session CSV"
DESCRIPTION = (
    "Starts the sensor's centroid stream, records --frames frames with a progress bar, stops the stream and writes "
    "SESSION.csv (frame, t_utc, star_id, x_px, y_px, mag). Lost messages are counted from sequence numbers and "
    "reported. Centroids arrive in fixed point (2^-10 px) and are written exactly."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument("--frames", type=int, required=True, metavar="N", help="frames to record")
    parser.add_argument("--out", required=True, metavar="SESSION.csv", help="session file to write")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.errors import UserError
    from hostlink.progress import progress_bar
    from hostlink.sensor_client import StreamResult, frames_to_session, stream_frames
    from hostlink.session import write_session

    if args.frames < 1:
        raise UserError("--frames must be >= 1")
    result = StreamResult()
    try:
        with open_link_from_args(args) as link, progress_bar("frames", args.frames, enabled=not args.quiet) as advance:
            stream_frames(link, args.frames, progress=advance, result=result)
    except (UserError, KeyboardInterrupt) as exc:
        # nothing lost: the frames that did arrive before the link failed or the user pressed Ctrl-C are written
        if not result.frames:
            raise
        write_session(args.out, frames_to_session(result.frames), float_format="%.10f")
        saved = f"the {len(result.frames)} frames received before were written to {args.out}"
        if isinstance(exc, KeyboardInterrupt):
            print(f"hostlink stream: interrupted; {saved}", file=sys.stderr)
            return 130
        err = UserError(f"{exc}; {saved}")
        err.exit_code = exc.exit_code  # the same exit code as without the partial session
        raise err from None
    write_session(args.out, frames_to_session(result.frames), float_format="%.10f")
    lost = result.lost_messages
    note = f"; the sensor's stream ended after {len(result.frames)} frames" if result.ended else ""
    print(
        f"{args.out}: {len(result.frames)} frames, {result.n_stars} stars; lost {lost} message(s) by sequence "
        f"number, {result.corrupt_frames} corrupt{note}",
        file=sys.stderr,
    )
    return 0
