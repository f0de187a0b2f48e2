"""``hostlink export-c``: write the C99 protocol kit (``hostlink.portkit.export_c``)."""

from __future__ import annotations

import argparse

HELP = "write C99 headers and one C source for the wire protocol (messages, framing, CRC, parameter table, CAN ids)"
DESCRIPTION = (
    "Generates, from the single protocol definition, C99 headers and one C source for a firmware port: message type "
    "bytes and packed layouts with explicit little-endian encode/decode functions per message (no struct punning, "
    "no dynamic memory), the parameter table layout and its CRC-32, COBS serial framing with sequence number and "
    "CRC-32, CRC-16/CCITT, and the CAN identifiers and signal positions. Files: st_wire.h, st_messages.h, "
    "st_param_table.h, st_can.h, st_protocol.c; they compile with `cc -std=c99 -Wall -Wextra -Werror`. "
    "docs/port-kit.md explains their use."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write into (created if needed; files are replaced)")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import export_c

    for path in export_c(args.dir):
        print(path)
    return 0
