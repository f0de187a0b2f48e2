"""Link benchmarks (run on demand, not by pytest): streamed stars per second as a fraction of each link's physical
limit, and host-side decoding speed as a multiple of the fastest line rate.

    .venv/bin/python benchmarks/bench_links.py [--transports serial,can,modbus] [--frames 2000] [--out bench.json]

Per transport: start ``hostlink emulate --transport T`` (simulated sky, default line rate), stream N frames through
``open_link`` exactly as ``hostlink stream`` does, and time them from the first frame received to the last.

* Serial limit: baud / 10 bits per byte / (wire bytes per star, framing included: the frame header, sequence
  number, CRC, COBS overhead and delimiter of each frame, spread over its stars).
* Other transports: the link module's ``physical_limit_stars_per_s(frames, info)`` (hostlink/links/INTERFACE.md);
  CAN counts 135 bits per worst-case (stuffed) classic frame and one frame per star plus a frame header.
* Host decoding: the recorded frames re-encoded as the serial byte stream, then split, CRC-checked and decoded by
  the host code; the ratio is decoded stars per second over the fastest line's stars per second (serial at its
  baud, CAN at 1 Mbit/s), measured side by side in this run.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time

from hostlink.emulator.process import EmulatorProcess
from hostlink.files.atomic import write_text
from hostlink.links import TRANSPORTS, open_link, split_link_string
from protocol.framing import FrameSplitter, decode_frame, encode_frame
from protocol.messages import decode, encode

#: Worst-case bits of one classic CAN frame with 8 data bytes, bit stuffing included (issue 6).
CAN_BITS_PER_FRAME = 135
CAN_FASTEST_BITRATE = 1_000_000


def stream_rate(link, n_frames: int) -> tuple[list, float]:
    link.set_streaming(True)
    frames = [link.recv_frame(5.0)]
    start = time.perf_counter()
    for _ in range(n_frames):
        frame = link.recv_frame(5.0)
        if frame is None:
            break
        frames.append(frame)
    elapsed = time.perf_counter() - start
    link.set_streaming(False)
    return frames, elapsed


def serial_wire(frames) -> bytes:
    return b"".join(encode_frame(k, encode(f)) for k, f in enumerate(frames))


def serial_limit_stars_per_s(frames, baud: int) -> float:
    stars = sum(f.n_stars for f in frames)
    return baud / 10.0 / (len(serial_wire(frames)) / stars)


def can_limit_stars_per_s(frames, bitrate: int = CAN_FASTEST_BITRATE) -> float:
    stars = sum(f.n_stars for f in frames)
    can_frames = stars + len(frames)  # one per star plus one header per sensor frame
    return bitrate / CAN_BITS_PER_FRAME / (can_frames / stars)


def host_decode_stars_per_s(frames, repeats: int = 5) -> float:
    wire = serial_wire(frames)
    stars = sum(f.n_stars for f in frames)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        splitter = FrameSplitter()
        n = 0
        for k in range(0, len(wire), 4096):  # as a port delivers it: arbitrary pieces
            for raw in splitter.feed(wire[k : k + 4096]):
                n += decode(decode_frame(raw).payload).n_stars
        best = min(best, time.perf_counter() - t0)
        assert n == stars
    return stars / best


def bench_transport(transport: str, n_frames: int) -> dict:
    with EmulatorProcess(transport) as emulator:
        info = emulator.info
        scheme, _ = split_link_string(info["link"])
        with open_link(info["link"], timeout_s=5.0) as link:
            frames, elapsed = stream_rate(link, n_frames)
            lost = link.stats.lost_messages
    timed = frames[1:]
    stars = sum(f.n_stars for f in timed)
    achieved = stars / elapsed
    if transport == "serial":
        limit = serial_limit_stars_per_s(timed, int(info.get("baud", 921_600)))
    else:
        hook = getattr(importlib.import_module(TRANSPORTS[scheme]), "physical_limit_stars_per_s", None)
        limit = hook(timed, info) if hook else float("nan")
    return {
        "transport": transport,
        "link": info["link"],
        "frames": len(timed),
        "stars": stars,
        "seconds": elapsed,
        "stars_per_s": achieved,
        "limit_stars_per_s": limit,
        "fraction_of_limit": achieved / limit,
        "lost_messages": lost,
        "frames_sample": frames,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transports", default="serial,can,modbus")
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--out", help="write the results as JSON here")
    args = parser.parse_args(argv)
    results = []
    for transport in [t.strip() for t in args.transports.split(",") if t.strip()]:
        try:
            results.append(bench_transport(transport, args.frames))
        except Exception as exc:  # noqa: BLE001 - one transport failing must not hide the others
            print(f"{transport}: not measured ({type(exc).__name__}: {exc})")
    if not results:
        return 1
    sample = next(r["frames_sample"] for r in results)
    serial_baud = 921_600
    line_rates = {
        f"serial@{serial_baud}": serial_limit_stars_per_s(sample[1:], serial_baud),
        f"can@{CAN_FASTEST_BITRATE}": can_limit_stars_per_s(sample[1:]),
    }
    fastest = max(line_rates.values())
    decode_rate = host_decode_stars_per_s(sample[1:])
    print(f"{'transport':10s} {'stars/s':>10s} {'limit':>10s} {'fraction':>9s} {'lost':>5s}")
    for r in results:
        print(
            f"{r['transport']:10s} {r['stars_per_s']:10.0f} {r['limit_stars_per_s']:10.0f} "
            f"{r['fraction_of_limit']:9.3f} {r['lost_messages']:5d}"
        )
    print(
        f"host decoding: {decode_rate:.0f} stars/s = {decode_rate / fastest:.1f} x the fastest line "
        f"({max(line_rates, key=line_rates.get)}, {fastest:.0f} stars/s)"
    )
    if args.out:
        for r in results:
            r.pop("frames_sample")
        write_text(
            args.out,
            json.dumps(
                {
                    "links": results,
                    "line_rates_stars_per_s": line_rates,
                    "host_decode_stars_per_s": decode_rate,
                    "host_decode_over_fastest_line": decode_rate / fastest,
                },
                indent=2,
            ),
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
