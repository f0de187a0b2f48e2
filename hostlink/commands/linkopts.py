"""The ``--link`` and ``--timeout`` options shared by every command that talks to a sensor."""

from __future__ import annotations

import argparse

from hostlink.api import UserError

LINK_HELP = (
    "sensor link string (docs/links.md), e.g. serial:/dev/ttyUSB0@921600, "
    "can:slcan:socket://127.0.0.1:5000@1000000, modbus-tcp:127.0.0.1:5020; `hostlink emulate` prints one"
)


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--link", required=True, help=LINK_HELP)
    parser.add_argument(
        "--timeout", type=float, default=2.0, metavar="S", help="longest wait for a reply or a frame [s] (default 2)"
    )


def open_link_from_args(args: argparse.Namespace):
    """The link named by ``--link``, with the ``--timeout`` checked (one-line UserError otherwise)."""
    from hostlink.api import open_link

    if not args.timeout > 0:
        raise UserError(f"--timeout must be > 0, got {args.timeout}")
    return open_link(args.link, timeout_s=args.timeout)
