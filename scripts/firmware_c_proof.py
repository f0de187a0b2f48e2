"""The acceptance run of the C firmware core against the Python reference model (issue 27), on demand:

    python scripts/firmware_c_proof.py --sequences 10000 --fuzz 100000 --seed 1

``--sequences N``: N random command sequences (1-40 steps each, the generator of tests/firmware_twins.py: uploads of
good and refused sets, chunks, verifies, commits with right and wrong nonces and generations, non-commands, exposures
and stream starts, reboots, power cuts), each on a sensor of its own identity; the replies and the flash images are
compared byte for byte after every step, and at the end of each sequence each firmware's flash image is booted by the
other (``Twins.cross_boot``: the same READ_ACTIVE, GET_STATUS, next STAGE_BEGIN nonce and flash bytes). ``--fuzz N``:
N mutated or random messages to one pair of sensors, the same verdict (no reply / the same reply bytes).
``--sanitize``: the C core built with AddressSanitizer and UndefinedBehaviorSanitizer (every finding fatal: the run
then dies with the sanitizer's report and a non-zero status); the script runs itself again with the ASan runtime
preloaded, as a non-instrumented Python needs. Prints the figures (steps, commits, refusals by code, answered fuzz
inputs) and exits 1 on the first difference, with the step that showed it.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import firmware_twins  # noqa: E402
from firmware_twins import Twins  # noqa: E402
from test_firmware_c import fuzz_input  # noqa: E402

from hostlink.portkit import firmware_c  # noqa: E402
from protocol.messages import NakCode  # noqa: E402

#: Set in the re-run process that has the ASan runtime preloaded.
_SANITIZED_RUN = "HOSTLINK_FWC_PROOF_SANITIZED"


def _rerun_sanitized(argv: list[str]) -> int:
    """This script again, in a process with the ASan runtime preloaded (Python's leaks at exit are not the core's:
    leak detection off; the core allocates nothing)."""
    preload = firmware_c.sanitizer_preload()
    if preload is None:
        print("error: the C compiler has no AddressSanitizer runtime (libasan.so)", file=sys.stderr)
        return 2
    firmware_c.build_library(extra=firmware_c.SANITIZE_FLAGS)  # a compiler error here is a one-line message
    env = dict(
        os.environ,
        LD_PRELOAD=preload,
        ASAN_OPTIONS="detect_leaks=0:abort_on_error=1",
        UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1",
        **{_SANITIZED_RUN: "1"},
    )
    return subprocess.run([sys.executable, __file__, *argv], env=env).returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=10_000)
    parser.add_argument("--fuzz", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sanitize", action="store_true", help="the C core built with ASan and UBSan")
    args = parser.parse_args(argv)
    if args.sanitize and not os.environ.get(_SANITIZED_RUN):
        return _rerun_sanitized(sys.argv[1:] if argv is None else argv)
    if args.sanitize:
        firmware_twins.LIBRARY = firmware_c.load_library(sanitize=True)
    rng = random.Random(args.seed)
    start = time.perf_counter()
    steps = commits = crossed_committed = 0
    refusals: dict[int, int] = {}
    where = "start"
    try:
        for k in range(args.sequences):
            where = f"sequence {k}"
            identity = rng.getrandbits(16)
            twins = Twins(identity)
            for _ in range(rng.randint(1, 40)):
                twins.step(rng.randrange(17), rng.getrandbits(32), rng.getrandbits(16), rng.getrandbits(8))
            crossed_committed += twins.cross_boot(identity) > 1
            steps += twins.steps
            commits += twins.commits
            for code, count in twins.refusals.items():
                refusals[code] = refusals.get(code, 0) + count
        where = "fuzz"
        twins = Twins(args.seed)
        answered = 0
        for _ in range(args.fuzz):
            answered += twins.send(fuzz_input(rng, twins)) is not None
    except AssertionError as exc:
        print(f"DIFFERENCE in {where}: {exc}")
        return 1
    named = ", ".join(f"{NakCode(c).name} {n}" for c, n in sorted(refusals.items()))
    print(
        f"{args.sequences} sequences, {steps} steps, {commits} commits, refusals: {named}; "
        f"{args.sequences} cross-boots ({crossed_committed} of images holding a committed set); "
        f"{args.fuzz} fuzz inputs, {answered} answered; 0 differences in replies, flash images and cross-boots"
        f"{'; C core under ASan+UBSan, no finding' if args.sanitize else ''} ({time.perf_counter() - start:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
