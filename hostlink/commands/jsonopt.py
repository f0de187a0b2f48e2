"""``--json`` of the batch commands (issue 31): one JSON object on stdout, with the same keys as the file the command
writes, instead of the human report; progress, warnings and errors stay on stderr."""

from __future__ import annotations

import argparse


def add_json_argument(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument(
        "--json",
        action="store_true",
        help=f"print {what} as one JSON object on stdout (the same keys as the file), instead of the report; "
        "errors stay on stderr",
    )


def print_json(data: object) -> None:
    """``data`` as strict JSON (no NaN: null), one object, on stdout."""
    import sys

    from hostlink.api import json_text

    sys.stdout.write(json_text(data))
    sys.stdout.flush()
