"""CAN and Modbus link benchmarks (run on demand, not by pytest), measured side by side in one run:

    .venv/bin/python benchmarks/bench_can_modbus.py [--frames 1500] [--bitrates 500000,1000000] [--out bench.json]

* CAN stream: ``hostlink emulate --transport can --bitrate B`` as a separate process, the host reading through
  python-can's ``slcan`` interface (``open_link`` exactly as ``hostlink stream``), timed from the first frame to the
  last. Limit = bitrate / 135 bits per worst-case frame / CAN frames per star (``can_link.physical_limit_stars_per_s``,
  headers and time bases included). Target: >= 0.90 of the limit.
* Host decoding: the recorded frames as the CAN frames the sensor sends (time base, header, stars), decoded by the
  host's ``StreamAssembler``; stars/s over the fastest line's stars/s (CAN at 1 Mbit/s). Target: >= 10x. The same
  ratio is printed for python-can's SLCAN ASCII parsing of those frames (the adapter driver, not our protocol).
* Modbus TCP and RTU-over-TCP stream: stars/s and register transactions/s (loopback has no line rate to compare with).
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time

import can

from hostlink.emulator.process import EmulatorProcess
from hostlink.emulator.slcan_hub import HubFrame, format_slcan_frame
from hostlink.files.atomic import write_text
from hostlink.links import open_link
from hostlink.links.can_link import (
    StreamAssembler,
    _buffered_socket_url,
    can_frames_for,
    physical_limit_stars_per_s,
)
from protocol import can_frames as cf

FASTEST_CAN_BITRATE = 1_000_000


def stream(link_string: str, n_frames: int) -> tuple[list, float, int]:
    with open_link(link_string, timeout_s=5.0) as link:
        link.set_streaming(True)
        frames = [link.recv_frame(5.0)]
        start = time.perf_counter()
        while len(frames) <= n_frames:
            frame = link.recv_frame(5.0)
            if frame is None:
                break
            frames.append(frame)
        elapsed = time.perf_counter() - start
        link.set_streaming(False)
        return frames[1:], elapsed, link.stats.lost_messages


def can_wire(frames) -> list[tuple[int, bytes]]:
    """(identifier, payload) of every CAN frame the sensor sends for ``frames`` (protocol.can_frames.StreamEncoder,
    as hostlink.emulator.can_endpoint)."""
    encoder = cf.StreamEncoder()
    return [pair for f in frames for pair in encoder.encode(f)]


def best_of(repeat: int, fn) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def host_decode_stars_per_s(frames, repeat: int = 5) -> float:
    wire = can_wire(frames)
    stars = sum(f.n_stars for f in frames)

    def run() -> None:
        asm = StreamAssembler()
        n = 0
        for fid, data in wire:
            out = asm.feed(fid, data)
            if out is not None:
                n += out.n_stars
        assert n == stars and asm.lost == 0

    return stars / best_of(repeat, run)


def slcan_parse_stars_per_s(frames, scheme: str = "socket") -> float:
    """python-can's slcan reader on the same frames as SLCAN text, pre-buffered in a local socket, opened as
    ``socket://`` (pyserial) or ``bufsocket://`` (hostlink.links.urlhandler, what CanLink uses)."""
    wire = b"".join(format_slcan_frame(HubFrame(fid, False, False, 8, data)) for fid, data in can_wire(frames))
    stars = sum(f.n_stars for f in frames)
    server = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        conn, _ = server.accept()
        conn.recv(64)
        conn.sendall(wire)
        time.sleep(2)
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    url = f"socket://127.0.0.1:{server.getsockname()[1]}"
    bus = can.Bus(
        interface="slcan", channel=_buffered_socket_url(url) if scheme == "bufsocket" else url, sleep_after_open=0
    )
    n_can = can_frames_for(frames)
    t0 = time.perf_counter()
    got = 0
    while got < n_can and bus.recv(1.0) is not None:
        got += 1
    elapsed = time.perf_counter() - t0
    bus.shutdown()
    server.close()
    return stars / elapsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1500)
    parser.add_argument("--bitrates", default="500000,1000000")
    parser.add_argument("--modbus-frames", type=int, default=500)
    parser.add_argument("--out")
    args = parser.parse_args(argv)
    can, can_frames = _can_runs([int(b) for b in args.bitrates.split(",") if b], args.frames)
    modbus, modbus_frames = _modbus_runs(args.modbus_frames)
    results = {"can": can, "modbus": modbus, "host_decode": _host_decode(can_frames or modbus_frames)}
    _print_results(results)
    if args.out:
        write_text(args.out, json.dumps(results, indent=2))
    return 0


def _can_runs(bitrates: list[int], n_frames: int) -> tuple[list[dict], list | None]:
    """``n_frames`` streamed from an emulated CAN sensor at each bit rate: the rate against the line's limit; and
    the first run's frames (None without a bit rate)."""
    runs, sample = [], None
    for bitrate in bitrates:
        with EmulatorProcess("can", ["--bitrate", str(bitrate)]) as emulator:
            info = emulator.info
            frames, elapsed, lost = stream(info["link"], n_frames)
        stars = sum(f.n_stars for f in frames)
        limit = physical_limit_stars_per_s(frames, info)
        runs.append(
            {
                "bitrate": bitrate,
                "frames": len(frames),
                "stars": stars,
                "seconds": elapsed,
                "stars_per_s": stars / elapsed,
                "limit_stars_per_s": limit,
                "fraction_of_limit": stars / elapsed / limit,
                "lost": lost,
            }
        )
        sample = sample or frames
    return runs, sample


def _modbus_runs(n_frames: int) -> tuple[list[dict], list]:
    """``n_frames`` streamed from an emulated Modbus sensor over TCP and over RTU; and the first run's frames."""
    runs, sample = [], None
    for key in ("link", "link_rtu"):
        with EmulatorProcess("modbus") as emulator:
            info = emulator.info
            frames, elapsed, lost = stream(info[key], n_frames)
            stars = sum(f.n_stars for f in frames)
            runs.append(
                {
                    "link": key,
                    "frames": len(frames),
                    "stars": stars,
                    "seconds": elapsed,
                    "stars_per_s": stars / elapsed,
                    "frames_per_s": len(frames) / elapsed,
                    "lost": lost,
                }
            )
            sample = sample or frames
    return runs, sample


def _host_decode(sample) -> dict:
    """The host's decoding rates of the frames ``sample`` (its own CAN decoder, python-can's SLCAN over a socket
    and a buffered socket), against the fastest CAN line's star rate."""
    fastest = physical_limit_stars_per_s(sample, {"bitrate": FASTEST_CAN_BITRATE})
    decode = host_decode_stars_per_s(sample)
    return {
        "stars_per_s": decode,
        "fastest_line_stars_per_s": fastest,
        "ratio": decode / fastest,
        "slcan_socket_stars_per_s": slcan_parse_stars_per_s(sample),
        "slcan_bufsocket_stars_per_s": slcan_parse_stars_per_s(sample, "bufsocket"),
    }


def _print_results(results: dict) -> None:
    print(f"{'CAN bit rate':>12s} {'stars/s':>9s} {'limit':>9s} {'fraction':>9s} {'lost':>5s}")
    for r in results["can"]:
        print(
            f"{r['bitrate']:12d} {r['stars_per_s']:9.0f} {r['limit_stars_per_s']:9.0f} "
            f"{r['fraction_of_limit']:9.3f} {r['lost']:5d}"
        )
    for r in results["modbus"]:
        print(
            f"modbus {r['link']:8s}: {r['stars_per_s']:.0f} stars/s, {r['frames_per_s']:.0f} frames/s "
            f"(>= 2 register transactions each), lost {r['lost']}"
        )
    h = results["host_decode"]
    decode, fastest = h["stars_per_s"], h["fastest_line_stars_per_s"]
    slcan, slcan_buf = h["slcan_socket_stars_per_s"], h["slcan_bufsocket_stars_per_s"]
    print(
        f"host CAN stream decoding: {decode:.0f} stars/s = {decode / fastest:.1f} x the fastest line "
        f"(CAN @ 1 Mbit/s: {fastest:.0f} stars/s)"
    )
    print(
        f"python-can slcan reading the same frames as SLCAN text: socket:// {slcan:.0f} stars/s "
        f"({slcan / fastest:.2f} x), bufsocket:// {slcan_buf:.0f} stars/s ({slcan_buf / fastest:.2f} x)"
    )


if __name__ == "__main__":
    sys.exit(main())
