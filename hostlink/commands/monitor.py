"""``hostlink monitor``: watch the sensor's onboard recursive estimate."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

#: Polls in a row whose reply may be lost while the stream keeps delivering frames (a busy host or bus); one more,
#: or a stream that stops, ends the monitor with the link error (exit 3).
MISSED_POLLS_ALLOWED = 3

HELP = "watch the onboard estimate (values, 1-sigma, updates) while the sensor runs"
DESCRIPTION = (
    "Polls the sensor's onboard recursive estimate every --interval seconds (or every --every-frames frames) and "
    "prints one line per poll: frames received, the frame of the estimate's last update, updates, and each estimated "
    "parameter with its 1-sigma (f in mm, x0/y0 in px); 'no estimate' until the estimator has processed a frame. "
    "A poll whose reply is lost while frames keep arriving is reported and the monitor goes on (up to 3 in a row). "
    "By default it keeps the centroid stream on (an emulated sensor only takes exposures while streaming) and "
    "discards the frames."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument(
        "--count", type=int, default=10, metavar="N", help="polls before exiting (default 10; 0 = until interrupted)"
    )
    parser.add_argument("--interval", type=float, default=1.0, metavar="S", help="seconds between polls (default 1)")
    parser.add_argument(
        "--every-frames",
        type=int,
        default=0,
        metavar="K",
        help="poll after every K frames received instead of every --interval seconds (a schedule that does not "
        "depend on the speed of either machine)",
    )
    parser.add_argument("--no-stream", action="store_true", help="do not switch the centroid stream on")
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of text")


def run(args: argparse.Namespace) -> int:
    import json

    from hostlink.api import EstimatePoll, UserError, estimate_record, poll_estimates, stream_frames

    if args.count < 0 or args.interval <= 0 or args.every_frames < 0:
        raise UserError("--count and --every-frames must be >= 0 and --interval > 0")
    if args.no_stream and args.every_frames:
        raise UserError("--every-frames needs the stream (drop --no-stream)")

    def show(poll: EstimatePoll) -> None:
        record = estimate_record(poll)
        if args.json:
            print(json.dumps(record), flush=True)
        elif not poll.answered:
            print(f"frames {poll.frames_received} poll not answered (the stream goes on): {poll.reason}", flush=True)
        elif poll.estimate is None:
            print(f"frames {poll.frames_received} no estimate: {poll.reason}", flush=True)
        else:
            values, sigmas = record["values"], record["sigma"]
            parts = " ".join(f"{n}={values[n]:.7g}\u00b1{_sigma_text(sigmas[n])}" for n in values)
            print(
                f"frames {poll.frames_received} frame {record['frame']} updates {record['updates']} {parts}", flush=True
            )

    max_polls = args.count or None
    with open_link_from_args(args) as link:
        if args.no_stream:
            poll_estimates(link, max_polls, args.interval, show)
        else:
            stream_frames(
                link,
                None,
                frame_timeout_s=args.timeout,
                keep_frames=False,
                poll_every_frames=args.every_frames,
                poll_every_s=0.0 if args.every_frames else args.interval,
                max_polls=max_polls,
                on_poll=show,
                keep_polls=False,  # shown, not kept: a monitor left running must not grow
                missed_polls_allowed=MISSED_POLLS_ALLOWED,
            )
    return 0


def _sigma_text(sigma: float | None) -> str:
    return "nan" if sigma is None else f"{sigma:.2g}"
