"""``hostlink vectors``: write the golden test vectors of the onboard reference model (``hostlink.portkit.vectors``)."""

from __future__ import annotations

import argparse

HELP = "write golden test vectors (float32 and fixed point, with tolerances) for proving a C port of the sensor"
DESCRIPTION = (
    "Writes one JSON file per onboard function and precision into DIR (pixel to direction, camera Jacobians, "
    "interstar residual and its Jacobian, one U-D update, refraction by addition, apparent place, attitude, bank "
    "record encode/verify; NAME.float32.json, NAME.fixed.json where the sensor without an FPU runs it in integers, "
    "bank_record.bytes.json) and index.json. Each file holds inputs and reference outputs bit-exact (IEEE-754 bit "
    "patterns in hex, integers as decimal strings) and, per output, the tolerance a port must meet and why "
    "(float32: gamma_n of the magnitudes the operations act on; fixed point and bytes: exact). Prints the cost "
    "table too (as `hostlink costs`). docs/port-kit.md explains the files."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write into (created if needed; files are replaced)")
    parser.add_argument(
        "--stars", type=int, default=32, metavar="N", help="stars per frame of the cost table (default 32)"
    )
    parser.add_argument("--quiet", action="store_true", help="print only the files written, not the cost table")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import cost_table_text, write_vectors

    for path in write_vectors(args.dir):
        print(path)
    if not args.quiet:
        print()
        print(cost_table_text(args.stars))
    return 0
