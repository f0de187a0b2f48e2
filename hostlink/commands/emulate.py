"""``hostlink emulate``: run an emulated sensor (the real onboard firmware) behind a serial, CAN or Modbus endpoint."""

from __future__ import annotations

import argparse

HELP = "run an emulated sensor until stopped; the first stdout line is JSON with the link string"
DESCRIPTION = (
    "Runs the onboard firmware (parameter banks, state machine, recursive estimator) behind a real link endpoint: "
    "a pty for serial (paced to --baud), python-can slcan on a TCP hub for CAN (paced to --bitrate), a Modbus "
    "server on 127.0.0.1. Frames come from the sky simulator, or from --replay SESSION.csv (streamed once, in file "
    "order). The first line on stdout is a JSON object whose key 'link' is what the other commands take as --link. "
    "Stop with Ctrl-C or SIGTERM."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--transport", required=True, choices=("serial", "can", "modbus"), help="link to emulate")
    _add_session_arguments(parser)
    _add_link_arguments(parser)
    _add_firmware_arguments(parser)
    _add_timing_and_fault_arguments(parser)


def _add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """What the sensor serves: a replayed session or one simulated from a nominal set or a camera."""
    parser.add_argument(
        "--replay", metavar="SESSION.csv", help="stream this session's frames (once) instead of the simulator"
    )
    parser.add_argument(
        "--nominal",
        metavar="PARAMS.json",
        help="the factory parameter set in bank A, generation 1 (default builtin:seed004_nominal, shipped with the "
        "package: a 1024 x 1024 px, 12 um, 70 mm, 10 deg camera (seed 004's design), principal point at the image "
        "centre, no distortion; "
        "`hostlink example` writes it as nominal.json)",
    )
    parser.add_argument(
        "--camera",
        metavar="CAMERA.json",
        help="the simulator's true camera (default builtin:seed004_camera: that camera as built: f 70.2262 mm, "
        "principal point (500, 530) px, radial distortion (seed 004's simulated camera); `hostlink example` writes "
        "it as true-camera.json)",
    )
    parser.add_argument(
        "--sim-frames", type=int, default=500, metavar="N", help="simulated frames, cycled forever (default 500)"
    )
    parser.add_argument(
        "--noise-px",
        type=float,
        default=0.05,
        help="simulated centroid noise [px], also the estimator's noise model (default 0.05)",
    )
    parser.add_argument("--seed", type=int, default=0, help="simulator seed")


def _add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """The link: serial baud rate, CAN bit rate, the port and the Modbus unit."""
    parser.add_argument("--baud", type=int, default=921_600, help="serial / Modbus RTU baud rate (default 921600)")
    parser.add_argument("--bitrate", type=int, default=1_000_000, help="CAN bit rate (default 1000000)")
    parser.add_argument("--port", type=int, default=0, help="TCP port for CAN hub / Modbus TCP (default: a free one)")
    parser.add_argument("--unit", type=int, default=1, help="Modbus unit (slave) id (default 1)")


def _add_firmware_arguments(parser: argparse.ArgumentParser) -> None:
    """The sensor inside: the estimator, its precision, the firmware (Python or C), the flash and its budget."""
    parser.add_argument(
        "--estimate",
        metavar="NAMES",
        help="parameters the onboard estimator estimates (comma-separated, default all: f,x0,y0,k1,k2,k3,p1,p2,s1,s2)",
    )
    parser.add_argument("--no-estimator", action="store_true", help="run without the onboard recursive estimator")
    parser.add_argument(
        "--precision",
        choices=("float32", "fixed"),
        default="float32",
        help="the sensor's arithmetic: float32 (a single-precision FPU, the default) or fixed (no FPU: the estimator's "
        "per-star front end in integers, Q10 centroids and Q30 unit vectors, its filter in soft float32)",
    )
    parser.add_argument(
        "--firmware",
        choices=("python", "c"),
        default=None,
        help="the sensor's firmware: python (the reference model, the default) or c (the C core of onboard/c, built "
        "once with this machine's C compiler and run in the emulator: software in the loop); the default can be set "
        "with the environment variable HOSTLINK_FIRMWARE (a test run of the link suites against the C core)",
    )
    parser.add_argument(
        "--flash",
        metavar="FILE",
        help="keep the sensor's parameter banks, generation and staging-session counters in this NOR-flash image "
        "(created blank, then given the --nominal set, if new); a restart on the same file boots the last committed "
        "set, and killing the emulator at any moment leaves the complete old or new set (default: banks in RAM)",
    )
    parser.add_argument(
        "--power-cut-after",
        type=int,
        metavar="UNITS",
        help="testing, with --flash: the emulator kills itself (SIGKILL) after writing this many 8-byte flash units "
        "from its start, a power cut at an exact byte of an erase or program",
    )
    parser.add_argument(
        "--estimator-mflops",
        type=float,
        default=50.0,
        metavar="MFLOPS",
        help="the modelled sensor processor's sustained speed [Mflop/s] (default 50, a Cortex-M7-class FPU): the "
        "estimator processes an exposure when its declared worst-case cost has finished before the exposure's time, "
        "whatever the speed of this machine (frames it has no time for are skipped and counted)",
    )


def _add_timing_and_fault_arguments(parser: argparse.ArgumentParser) -> None:
    """The replay's phase starts, messages lost on purpose (testing) and transport-specific settings."""
    parser.add_argument(
        "--phase-start",
        type=int,
        action="append",
        default=[],
        metavar="FRAME",
        help="with --replay (repeatable): the frame counter where a phase of the replay begins, as a bench's scene "
        "generator switches scenes; a stream started again after an exposure begins at the next phase start past "
        "it, so the exposures taken while the host stopped the previous stream never shift the next phase",
    )
    parser.add_argument(
        "--drop-every",
        type=int,
        default=0,
        metavar="K",
        help="testing: lose every Kth streamed message on the line (default 0 = never)",
    )
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="transport-specific setting (repeatable); modbus: rtu_port=PORT, the RTU-over-TCP server's TCP port "
        "(default: a free one); an unknown key is refused",
    )


def run(args: argparse.Namespace) -> int:
    import importlib
    import json
    import math
    import os
    import signal
    import sys
    import threading

    from hostlink.api import (
        ENDPOINTS,
        EndpointOptions,
        EstimatorBudget,
        UserError,
        build_sensor,
        parse_endpoint_options,
    )

    extra = parse_endpoint_options(args.transport, args.option)
    for name in ("baud", "bitrate", "sim_frames"):
        if getattr(args, name) <= 0:
            raise UserError(f"--{name.replace('_', '-')} must be > 0")
    if not 0 <= args.port < 65536:
        raise UserError("--port must be in 0..65535")
    if not 1 <= args.unit <= 247:  # Modbus: 0 is the broadcast address, which a device never answers; 248-255 reserved
        raise UserError(f"--unit must be a Modbus device address 1..247, got {args.unit}")
    if args.power_cut_after is not None and (args.flash is None or args.power_cut_after < 0):
        raise UserError("--power-cut-after needs --flash and a count >= 0")
    if args.drop_every < 0:
        raise UserError("--drop-every must be >= 0")
    if not (math.isfinite(args.estimator_mflops) and args.estimator_mflops > 0):
        raise UserError(f"--estimator-mflops must be > 0, got {args.estimator_mflops}")
    sensor = build_sensor(
        replay=args.replay,
        nominal=args.nominal,
        camera=args.camera,
        sim_frames=args.sim_frames,
        noise_px=args.noise_px,
        seed=args.seed,
        estimator=not args.no_estimator,
        estimate_names=args.estimate,
        budget=EstimatorBudget(flops_per_s=args.estimator_mflops * 1e6),
        flash=args.flash,
        power_cut_after_units=args.power_cut_after,
        precision=args.precision,
        firmware=args.firmware or os.environ.get("HOSTLINK_FIRMWARE") or "python",
        phase_starts=tuple(args.phase_start),
    )
    options = EndpointOptions(
        baud=args.baud, bitrate=args.bitrate, port=args.port, unit=args.unit, drop_every=args.drop_every, extra=extra
    )
    try:
        endpoint = importlib.import_module(ENDPOINTS[args.transport])
    except ModuleNotFoundError as exc:
        if exc.name == ENDPOINTS[args.transport]:
            raise UserError(f"the {args.transport} emulator is not available in this build") from None
        raise
    stop = threading.Event()

    def on_signal(_signum, _frame):  # the signal handler signature
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    def ready(info: dict) -> None:
        sys.stdout.write(json.dumps(info) + "\n")
        sys.stdout.flush()

    endpoint.serve(sensor, options, ready, stop)
    return 0
