"""``hostlink params``: print a sensor's active parameters as a camera parameter file."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

HELP = "print the sensor's active parameters as a camera parameter file"
DESCRIPTION = (
    "Reads the active parameter set (with its generation and CRC) and prints it as a camera parameter file (JSON) "
    "on stdout, each value as the shortest decimal of the sensor's float32, with a 'sigma' object (the 1-sigma prior "
    "the sensor's estimator starts from; null = unknown) when the set has one. The generation and CRC go to stderr."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument("--out", metavar="PARAMS.json", help="also write the file here")


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.api import emit_param_file, params_float32_dict, read_active_params

    with open_link_from_args(args) as link:
        active = read_active_params(link)
    emit_param_file(params_float32_dict(active.params, active.sigma), args.out)
    print(f"generation {active.generation}, CRC 0x{active.crc32:08x}", file=sys.stderr)
    return 0
