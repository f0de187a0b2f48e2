"""``hostlink accept``: commit the sensor's onboard estimate through the safe upload."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

HELP = "commit the onboard estimate as the active parameter set (same safe path as upload)"
DESCRIPTION = (
    "Reads the active set and the onboard recursive estimate, forms the full parameter set (the active one with the "
    "estimated parameters replaced), and commits it through the six-step safe upload (validate, stage, verify, read "
    "back, commit to the inactive A/B bank, read back). The estimate's own 1-sigma travels with it as the new set's "
    "prior, so the estimator restarts from what it had learnt. Prints the committed set as a camera parameter file "
    "(with its 'sigma'). Only a converged estimate is committed: at least 300 updates (the estimator's burn-in) and "
    "every estimated parameter's 1-sigma at most a quarter of its cold-start prior (the data carry at least 15 times "
    "the prior's information); --force skips that test."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_link_arguments(parser)
    parser.add_argument("--out", metavar="PARAMS.json", help="also write the committed set here")
    parser.add_argument(
        "--force", action="store_true", help="commit the estimate even if it has not converged (testing, commissioning)"
    )


def run(args: argparse.Namespace) -> int:
    import sys

    from hostlink.api import accept_estimate, emit_param_file, params_float32_dict

    with open_link_from_args(args) as link:
        result, estimate = accept_estimate(link, force=args.force)
    emit_param_file(params_float32_dict(result.active, result.sigma), args.out)
    print(
        f"accepted the estimate after {estimate.n_updates} updates (frame {estimate.last_frame}): generation "
        f"{result.generation}, CRC 0x{result.crc32:08x}",
        file=sys.stderr,
    )
    return 0
