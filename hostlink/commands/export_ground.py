"""``hostlink export-ground``: write the COSMOS target and the XTCE document (``hostlink.portkit.export_ground``)."""

from __future__ import annotations

import argparse

HELP = "write OpenC3 COSMOS targets (serial and Modbus/TCP: commands, telemetry, interfaces) and an XTCE 1.2 document"
DESCRIPTION = (
    "Generates, from the single protocol definition, the sensor's messages for the ground systems test campaigns "
    "use: an OpenC3 COSMOS plugin (cosmos/plugin.txt: the serial interface with COSMOS's COBS and CRC-32 protocols "
    "configured to the project's framing, and a Modbus/TCP interface; cosmos/targets/STARTRACKER/: target.txt and "
    "cmd_tlm/cmd.txt, tlm.txt with every field's type, unit, description and states; cosmos/targets/STARTRACKER_MB/: "
    "the Modbus register map's reads and writes) and xtce/startracker.xml, an XTCE 1.2 document of the serial "
    "messages for Yamcs or any XTCE tool (written by yamcs-pymdb). docs/ground-systems.md explains how to load them, "
    "what maps to what and what does not translate."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write into (created if needed; files are replaced)")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import export_ground

    for path in export_ground(args.dir):
        print(path)
    return 0
