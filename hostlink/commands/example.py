"""``hostlink example``: write the worked session's starting files (``hostlink.mission.example``)."""

from __future__ import annotations

import argparse

HELP = "write the worked session's starting files (nominal and true camera, README.txt) into a directory"
DESCRIPTION = (
    "Writes DIR/nominal.json (what a user knows before calibrating: a 1024 x 1024 px, 12 um, 70 mm, 10 deg camera, "
    "principal point at the image centre, no distortion), DIR/true-camera.json (the camera the simulator looks "
    "through: f 70.2262 mm, principal point (500, 530) px, radial distortion) and DIR/README.txt (the commands of "
    "the worked session: simulate, calibrate, replay, attitude, then an emulated sensor). The files come with the "
    "package: no repository checkout is needed."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", metavar="DIR", help="directory to write into (created if needed)")
    parser.add_argument("--force", action="store_true", help="replace example files that already exist in DIR")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import write_example

    result = write_example(args.dir, overwrite=args.force)
    for path in result.written:
        print(path)
    print(f"next: cd {result.directory} and follow README.txt")
    return 0
