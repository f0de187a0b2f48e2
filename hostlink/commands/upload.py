"""``hostlink upload``: the six-step safe upload of a camera parameter file to a sensor."""

from __future__ import annotations

import argparse

from hostlink.commands.linkopts import add_link_arguments, open_link_from_args

HELP = "validate, upload, verify and commit a parameter file on a sensor (A/B banks)"
DESCRIPTION = (
    "Safe upload: 1. check the set's plausibility on the host (finite values, principal point on the detector, a "
    "one-to-one distortion whose displacement stays within 5% of the half-diagonal, focal length within 5% of the "
    "active set's); 2. open a staging session (the sensor answers with a nonce) and stage the set in chunks; 3. the "
    "sensor checks its CRC and the same rules against its own design; 4. read the staged set back; 5. the sensor "
    "commits it to its inactive A/B bank with a new generation and switches atomically, only for this session's "
    "nonce and the generation read in step 1 (replayed traffic commits nothing); 6. read the active set back. A "
    "refusal names the rule on one line. Exit 0 only when the active parameters read "
    "back equal to the file (to float32). A refusal prints the sensor's reason on one line; an interrupted upload "
    "leaves the old set active. The file's 'sigma' object (1-sigma of each estimated parameter, as written by "
    "'hostlink calibrate' or 'hostlink replay') travels with the set: the sensor's onboard estimator restarts from "
    "it as its prior, so a refinement keeps the calibration's accuracy (null, NaN or 0 = unknown: cold-start prior). "
    "A file whose 'status' is 'failed' or 'not_converged' (a calibration kept with --keep-failed, a replay that did "
    "not converge) is refused before anything is sent (exit 2); a file without a status (a design nominal, a "
    "hand-written set) is checked by the plausibility rules only."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "params",
        metavar="PARAMS.json",
        help="camera parameter file (a path, or builtin:NAME for one shipped with the package)",
    )
    add_link_arguments(parser)
    parser.add_argument(
        "--no-host-check",
        action="store_true",
        help="skip step 1 (testing: let the sensor's own checks refuse a bad set)",
    )
    parser.add_argument("--verbose", action="store_true", help="print each step")


def run(args: argparse.Namespace) -> int:
    import sys

    import numpy as np

    from hostlink.api import UserError, float32_equal, load_params_for_upload, refined_mask, safe_upload

    params, sigma = load_params_for_upload(args.params, validate=not args.no_host_check)  # refuses a failed set

    def step(k: int, text: str) -> None:
        if args.verbose:
            print(f"step {k}/6: {text}", file=sys.stderr)

    with open_link_from_args(args) as link:
        result = safe_upload(link, params, host_check=not args.no_host_check, step=step, sigma=sigma)
    # safe_upload compared the bytes; this is the user's promise
    if not float32_equal(result.active, params, result.sigma, sigma):
        raise UserError("the sensor's active parameters differ from the file")
    known = int(np.count_nonzero(refined_mask(sigma)))
    print(
        f"{args.params}: committed as generation {result.generation} (CRC 0x{result.crc32:08x}); active "
        f"parameters read back equal to the file (float32); sigma prior for {known} of 10 parameters",
        file=sys.stderr,
    )
    return 0
