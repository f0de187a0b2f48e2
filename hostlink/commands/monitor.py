"""``hostlink monitor``: watch the sensor's onboard recursive estimate."""

from __future__ import annotations

import argparse

from hostlink.linkopts import add_link_arguments, open_link_from_args

HELP = "watch the onboard estimate (values, 1-sigma, updates) while the sensor runs"
DESCRIPTION = (
    "Polls the sensor's onboard recursive estimate every --interval seconds and prints one line per poll: frame, "
    "updates, and each estimated parameter with its 1-sigma (f in mm, x0/y0 in px). By default it keeps the "
    "centroid stream on (an emulated sensor only takes exposures while streaming) and discards the frames."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument(
        "--count", type=int, default=10, metavar="N", help="polls before exiting (default 10; 0 = until interrupted)"
    )
    parser.add_argument("--interval", type=float, default=1.0, metavar="S", help="seconds between polls (default 1)")
    parser.add_argument("--no-stream", action="store_true", help="do not switch the centroid stream on")
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of text")


def run(args: argparse.Namespace) -> int:
    import json
    import math
    import time

    from hostlink.errors import UserError
    from hostlink.links import CommandRefused
    from protocol.messages import ESTIMATE_FIELDS, NakCode

    if args.count < 0 or args.interval <= 0:
        raise UserError("--count must be >= 0 and --interval > 0")
    polls = 0
    with open_link_from_args(args) as link:
        if not args.no_stream:
            link.set_streaming(True)
        try:
            while args.count == 0 or polls < args.count:
                deadline = time.monotonic() + args.interval
                while time.monotonic() < deadline:  # drain frames so they do not pile up
                    if args.no_stream:
                        time.sleep(max(0.0, deadline - time.monotonic()))
                    elif link.recv_frame(args.timeout) is None:
                        time.sleep(max(0.0, deadline - time.monotonic()))
                polls += 1
                try:
                    est = link.read_estimate()
                except CommandRefused as exc:
                    if exc.code != NakCode.NO_ESTIMATE:
                        raise
                    print(
                        json.dumps({"estimate": None, "reason": exc.text}) if args.json else f"no estimate: {exc.text}",
                        flush=True,
                    )
                    continue
                names = [n for i, n in enumerate(ESTIMATE_FIELDS) if est.estimated_mask >> i & 1]
                values = {n: est.values[ESTIMATE_FIELDS.index(n)] for n in names}
                sigmas = {n: est.sigma[ESTIMATE_FIELDS.index(n)] for n in names}
                if args.json:
                    print(
                        json.dumps(
                            {
                                "frame": est.last_frame,
                                "updates": est.n_updates,
                                "base_generation": est.base_generation,
                                "values": values,
                                "sigma": {k: (None if math.isnan(v) else v) for k, v in sigmas.items()},
                            }
                        ),
                        flush=True,
                    )
                else:
                    parts = " ".join(f"{n}={values[n]:.7g}\u00b1{sigmas[n]:.2g}" for n in names)
                    print(f"frame {est.last_frame} updates {est.n_updates} {parts}", flush=True)
        finally:
            if not args.no_stream:
                try:
                    link.set_streaming(False)
                except UserError:
                    pass
    return 0
