"""The link-integrity acceptance run (issue 15): stream through the fault-injecting relay on every transport and
check that no corrupt centroid is accepted, that the loss the link reports is the true loss, and that the stream
completes.

    python scripts/link_faults.py                      # 2,000 streamed frames per transport, BER 1e-4, 1 % drops
    python scripts/link_faults.py --frames 200 --transports serial,can
    python scripts/link_faults.py --both-directions    # the same faults on the host -> sensor line too
    python scripts/link_faults.py --seeds 1,2,3,4,5    # the acceptance run: five fault patterns per transport

One JSON line per transport and seed (``hostlink.emulator.fault_run.FaultRunResult``), then a summary line; exit code
1 if any run fails a check. The links are opened with the commands' default options (``--timeout`` 2 s, nothing
added to the link string). "Streamed frames" are frames the sensor sent, counted by frame counter from frame 0, the
emulator's first exposure: the true loss includes frames lost before the first one received. The faults are applied
sensor -> host, and with ``--both-directions`` host -> sensor too (the commands and, on Modbus, every read request).
Expect ~5 minutes per Modbus run of 2,000 frames: each lost answer costs one answer wait (~10 ms on 127.0.0.1), and
the sensor's stream window holds frames until the host has read them.
"""

from __future__ import annotations

import argparse
import json
import sys

from hostlink.emulator.fault_run import stream_through_faults
from hostlink.errors import LinkError

TRANSPORTS = {"serial": ("serial", False), "can": ("can", False), "modbus-tcp": ("modbus", False)}
TRANSPORTS["modbus-rtu"] = ("modbus", True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--ber", type=float, default=1e-4)
    parser.add_argument("--drop", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--seeds", default=None, help="comma-separated seeds, one run each (overrides --seed)")
    parser.add_argument("--transports", default=",".join(TRANSPORTS))
    parser.add_argument("--both-directions", action="store_true", help="faults on the host -> sensor line too")
    args = parser.parse_args()
    try:
        seeds = [int(v) for v in args.seeds.split(",")] if args.seeds else [args.seed]
    except ValueError:
        parser.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    names = args.transports.split(",")
    for name in names:
        if name not in TRANSPORTS:
            parser.error(f"unknown transport {name!r} (known: {', '.join(TRANSPORTS)})")
    ok = True
    for name in names:
        transport, rtu = TRANSPORTS[name]
        for seed in seeds:
            try:
                r = stream_through_faults(
                    transport,
                    args.frames,
                    ber=args.ber,
                    drop=args.drop,
                    seed=seed,
                    rtu=rtu,
                    both_directions=args.both_directions,
                )
            except LinkError as exc:  # the stream did not complete: a failed run, reported, the others go on
                ok = False
                print(json.dumps({"transport": name, "seed": seed, "error": str(exc), "pass": False}), flush=True)
                continue
            good = r.corrupt_accepted == 0 and r.reported_loss == r.true_loss and r.frames_spanned >= args.frames
            ok &= good
            print(json.dumps({**r.as_dict(), "seed": seed, "pass": good}), flush=True)
    print(json.dumps({"all_pass": ok}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
