"""``hostlink export-c``: write the C99 protocol kit (``hostlink.portkit.export_c``)."""

from __future__ import annotations

import argparse

HELP = (
    "write C99 headers and one C source for the wire protocol (messages, framing, CRC, parameter table, CAN ids) and "
    "the C firmware core beside them"
)
DESCRIPTION = (
    "Generates, from the single protocol definition, C99 headers and one C source for a firmware port: message type "
    "bytes and packed layouts with explicit little-endian encode/decode functions per message (no struct punning, "
    "no dynamic memory), the parameter table layout and its CRC-32, COBS serial framing with sequence number and "
    "CRC-32, CRC-16/CCITT, and the CAN identifiers and signal positions. Files: st_wire.h, st_messages.h, "
    "st_param_table.h, st_can.h, st_protocol.c; they compile with `cc -std=c99 -Wall -Wextra -Werror`. Beside "
    "them, the firmware core that uses them (onboard/c: firmware.c, the command state machine; banks.c, the "
    "parameter banks in NOR flash; params.c, the plausibility and sigma checks; pyformat.c; estimator_seam.h and its "
    "implementation; each .h says what it is), C99 with no dynamic memory and no I/O, the platform behind a HAL of "
    "callbacks; the whole tree compiles with -std=c99 -Wall -Wextra -Werror -pedantic -Wconversion -Wshadow. "
    "docs/port-kit.md explains their use and how to prove a port."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write into (created if needed; files are replaced)")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import export_c

    for path in export_c(args.dir):
        print(path)
    return 0
