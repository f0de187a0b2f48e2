"""``hostlink costs``: print the cost table of the onboard functions (``hostlink.portkit.costs``)."""

from __future__ import annotations

import argparse

HELP = "print operations and memory per frame of each onboard function (float32 and fixed point) at N stars"
DESCRIPTION = (
    "Prints, per onboard function a port needs, the multiplications, additions, divisions, square roots, "
    "trigonometric calls, shifts and comparisons of one frame at N stars (P = 2N - 3 pairs, K estimated "
    "parameters), and the working memory in bytes, in float32 and fixed point; the estimator's whole frame is the "
    "sensor's own budget model (onboard.recursive.update_cost_flops). Counted from the code; "
    "tests/test_portkit_costs.py holds the counts against an instrumented run."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stars", type=int, default=32, metavar="N", help="stars per frame (default 32, at least 3)")
    parser.add_argument("--states", type=int, default=10, metavar="K", help="estimated parameters (default 10, 1..10)")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import cost_table_text

    print(cost_table_text(args.stars, args.states))
    return 0
