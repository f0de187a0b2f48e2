"""``hostlink stream``: record centroid frames from a sensor into a session file."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

HELP = "record N centroid frames from a sensor into a session CSV"
DESCRIPTION = (
    "Starts the sensor's centroid stream, records --frames frames with a progress bar, stops the stream and writes "
    "SESSION.csv (frame, t_utc, star_id, x_px, y_px, mag), frame by frame as they arrive (into SESSION.csv.partial, "
    "renamed at the end; after Ctrl-C or a dropped link the frames received are kept). Lost messages are counted "
    "from sequence numbers and reported. Centroids arrive in fixed point (2^-10 px) and are written exactly."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument("--frames", type=int, required=True, metavar="N", help="frames to record")
    parser.add_argument("--out", required=True, metavar="SESSION.csv", help="session file to write")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.errors import UserError
    from hostlink.files.session import SessionWriter
    from hostlink.links.operations import StreamResult, frames_to_session, stream_frames
    from hostlink.progress import progress_bar

    if args.frames < 1:
        raise UserError("--frames must be >= 1")
    result = StreamResult()
    # every frame is written as it arrives (SESSION.csv.partial until the end): an interrupted or killed stream
    # loses nothing it had received
    writer = SessionWriter(args.out, float_format="%.10f")
    try:
        with open_link_from_args(args) as link, progress_bar("frames", args.frames, enabled=not args.quiet) as advance:
            stream_frames(
                link,
                args.frames,
                progress=advance,
                result=result,
                keep_frames=False,
                on_frame=lambda frame: writer.append(frames_to_session([frame])),
            )
    except (UserError, KeyboardInterrupt) as exc:
        if not result.frames_received:
            writer.close_partial()
            writer.partial.unlink(missing_ok=True)
            raise
        writer.commit()
        saved = f"the {result.frames_received} frames received before were written to {args.out}"
        if isinstance(exc, KeyboardInterrupt):
            print(f"hostlink stream: interrupted; {saved}", file=sys.stderr)
            return 130
        err = UserError(f"{exc}; {saved}")
        err.exit_code = exc.exit_code  # the same exit code as without the partial session
        raise err from None
    writer.commit()
    lost = result.lost_messages
    note = f"; the sensor's stream ended after {result.frames_received} frames" if result.ended else ""
    print(
        f"{args.out}: {result.frames_received} frames, {result.n_stars} stars; lost {lost} message(s) by sequence "
        f"number, {result.corrupt_frames} corrupt{note}",
        file=sys.stderr,
    )
    return 0
