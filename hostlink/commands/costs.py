"""``hostlink costs``: print the cost table of the onboard functions (``hostlink.portkit.costs``)."""

from __future__ import annotations

import argparse

HELP = (
    "print operations and memory per frame of each onboard function (float32 and fixed point) at N stars, or "
    "(--target) the C core's size, stack and instructions measured on an emulated Cortex-M"
)
DESCRIPTION = (
    "Prints, per onboard function a port needs, the multiplications, additions, divisions, square roots, "
    "trigonometric calls, shifts and comparisons of one frame at N stars (P = 2N - 3 pairs, K estimated "
    "parameters), and the working memory in bytes, in float32 and fixed point; the estimator's whole frame is the "
    "sensor's own budget model (onboard.recursive.update_cost_flops). Counted from the code; "
    "tests/test_portkit_costs.py holds the counts against an instrumented run. With --target (cortex-m4f, "
    "cortex-m0plus, or all): the C firmware core cross-compiled for that Cortex-M and run on an instruction-set "
    "emulator (the optional cortexm extra: pip install 'startracker-companion[cortexm]'): the golden vectors checked "
    "there, flash, RAM, the deepest stack, and exact instruction counts per recursive update at 8, 16 and 32 stars, "
    "per upload command and per refraction by addition (docs/port-kit.md)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stars", type=int, default=32, metavar="N", help="stars per frame (default 32, at least 3)")
    parser.add_argument("--states", type=int, default=10, metavar="K", help="estimated parameters (default 10, 1..10)")
    parser.add_argument(
        "--target",
        action="append",
        choices=("cortex-m4f", "cortex-m0plus", "all"),
        help="measure the C core on this emulated Cortex-M instead (repeatable; all = both)",
    )
    from hostlink.api import TARGET_COST_FRAMES

    parser.add_argument(
        "--frames",
        type=int,
        default=TARGET_COST_FRAMES,
        metavar="N",
        help=f"--target: updates per star count (default {TARGET_COST_FRAMES})",
    )
    parser.add_argument("--json", action="store_true", help="--target: print the measurements as one JSON object")
    parser.add_argument(
        "--optimise", choices=("O2", "Os"), default="O2", help="--target: the build's optimisation (default O2)"
    )


def run(args: argparse.Namespace) -> int:
    from hostlink.api import cost_table_text

    if args.target:
        return _run_targets(args)
    print(cost_table_text(args.stars, args.states))
    return 0


def _run_targets(args: argparse.Namespace) -> int:
    import json
    import sys

    from hostlink.api import format_target_costs as format_reports
    from hostlink.api import target_costs

    names = ["cortex-m4f", "cortex-m0plus"] if "all" in args.target else list(dict.fromkeys(args.target))
    progress = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    reports = target_costs(names, args.frames, progress=progress, optimise=args.optimise)
    if args.json:
        print(json.dumps({"targets": {r.target.name: r.as_json() for r in reports}}, indent=1))
    else:
        print(format_reports(reports))
    return 0 if all(r.vectors_passed for r in reports) else 1
