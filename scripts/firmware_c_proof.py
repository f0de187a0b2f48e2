"""The acceptance run of the C firmware core against the Python reference model (issue 27), on demand:

    python scripts/firmware_c_proof.py --sequences 10000 --fuzz 100000 --seed 1

``--sequences N``: N random command sequences (1-40 steps each, the generator of tests/firmware_twins.py: uploads of
good and refused sets, chunks, verifies, commits with right and wrong nonces and generations, non-commands, reboots,
power cuts), each on a sensor of its own identity; the replies and the flash images are compared byte for byte after
every step. ``--fuzz N``: N mutated or random messages to one pair of sensors, the same verdict (no reply / the same
reply bytes). Prints the figures (steps, commits, refusals by code, answered fuzz inputs) and exits 1 on the first
difference, with the step that showed it.
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from firmware_twins import Twins  # noqa: E402
from test_firmware_c import fuzz_input  # noqa: E402

from protocol.messages import NakCode  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=10_000)
    parser.add_argument("--fuzz", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)
    start = time.perf_counter()
    steps = commits = 0
    refusals: dict[int, int] = {}
    where = "start"
    try:
        for k in range(args.sequences):
            where = f"sequence {k}"
            twins = Twins(rng.getrandbits(16))
            for _ in range(rng.randint(1, 40)):
                twins.step(rng.randrange(17), rng.getrandbits(32), rng.getrandbits(16), rng.getrandbits(8))
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
        f"{args.fuzz} fuzz inputs, {answered} answered; 0 differences in replies and flash images "
        f"({time.perf_counter() - start:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
