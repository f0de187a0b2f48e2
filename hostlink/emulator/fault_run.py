"""Stream through the fault-injecting relay and score the result against the truth (the reliability suite's measure).

:func:`stream_through_faults` starts ``hostlink emulate`` (simulated sky, cycled), puts a
:mod:`~hostlink.emulator.fault_relay` in front of its link, streams ``n_frames`` frames with the one stream loop and
compares every frame received with the frame the sensor sent under the same frame counter (rebuilt here from the same
simulator options, on the wire's fixed-point grid). Scores:

* ``corrupt_accepted``: frames received whose counter, time or any star differ from the sensor's (must be 0);
* ``true_loss``: frames the sensor sent from its first, frame 0 (the emulator starts fresh, and its simulated
  source numbers exposures from 0), up to the last frame received, that did not arrive;
* ``reported_loss``: what the link counted (``Link.stats.lost_messages`` over the same span; must equal true_loss).

The link is opened with the commands' defaults (``--timeout`` 2 s, no link string options), as a user gets it.

Used by ``tests/test_link_fault_relay.py`` (short runs) and ``scripts/link_faults.py`` (the 2,000-frame run).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from hostlink.emulator.fault_relay import FaultModel, relay_link
from hostlink.emulator.process import EmulatorProcess
from hostlink.emulator.sensor import session_frames
from hostlink.emulator.setup import DEFAULT_CAMERA
from hostlink.files.params import load_params
from hostlink.links import open_link
from hostlink.links.base import DEFAULT_TIMEOUT_S
from hostlink.links.operations import StreamResult, stream_frames
from protocol.messages import CentroidFrame, dequantise_px, quantise_px

#: Centroid noise of the emulator's simulator (its --noise-px default), so the truth rebuilt here is its frames.
_NOISE_PX = 0.05


class _SpanDone(Exception):
    """Ends the stream once the sensor has streamed the frames asked for."""


@dataclass
class FaultRunResult:
    transport: str
    frames_received: int
    frames_spanned: int
    true_loss: int
    reported_loss: int
    corrupt_accepted: int
    corrupt_detected: int
    elapsed_s: float
    down: dict
    up: dict

    def as_dict(self) -> dict:
        return asdict(self)


def _truth(sim_frames: int, seed: int, n_needed: int) -> dict[int, CentroidFrame]:
    """The frames the emulator sends (``--sim-frames sim_frames --seed seed``), by frame counter."""
    from hostlink.sky.simulate import SimConfig, simulate

    sim = simulate(SimConfig(camera=load_params(DEFAULT_CAMERA), frames=sim_frames, noise_px=_NOISE_PX, seed=seed))
    out = {}
    for k, item in enumerate(session_frames(sim.session, cycle=True)):
        if k >= n_needed:
            break
        out[item.frame.frame] = item.frame
    return out


def _same_on_the_wire(got: CentroidFrame, sent: CentroidFrame, with_mag: bool) -> bool:
    grid = lambda v: dequantise_px(quantise_px(v))  # noqa: E731 - the wire's fixed-point grid
    ok = (
        got.frame == sent.frame
        and got.t_us == sent.t_us
        and np.array_equal(got.star_id, sent.star_id)
        and np.array_equal(got.x_px, grid(sent.x_px))
        and np.array_equal(got.y_px, grid(sent.y_px))
    )
    if ok and with_mag:
        ok = np.allclose(got.mag, sent.mag, atol=5e-4, equal_nan=True)  # millimagnitude steps: half a step
    return bool(ok)


def stream_through_faults(
    transport: str,
    n_frames: int,
    *,
    ber: float = 1e-4,
    drop: float = 0.01,
    seed: int = 0,
    sim_frames: int = 50,
    rtu: bool = False,
    frame_timeout_s: float | None = None,
    command_timeout_s: float = DEFAULT_TIMEOUT_S,
    emulator_args: tuple[str, ...] = (),
    both_directions: bool = False,
) -> FaultRunResult:
    """Stream from an emulated sensor through a relay with ``ber`` bit errors and ``drop`` byte drops in the sensor ->
    host direction until the sensor has streamed ``n_frames`` frames from frame 0 (frame counters);
    score them (see the module docstring). ``rtu``: Modbus RTU (over TCP). ``both_directions``: the same faults on the
    host -> sensor line too (its own seed). A link error (the stream did not complete) propagates."""
    args = ("--sim-frames", str(sim_frames), "--seed", str(seed), "--no-estimator", *emulator_args)
    down = FaultModel(ber=ber, drop=drop, seed=seed)
    up = FaultModel(ber=ber, drop=drop, seed=seed + 1) if both_directions else FaultModel(seed=seed + 1)
    with EmulatorProcess(transport, args) as emulator:
        link_string = emulator.info["link_rtu"] if rtu else emulator.link
        relayed, relay = relay_link(link_string, down, up)
        try:
            t0 = time.monotonic()
            with open_link(relayed, timeout_s=command_timeout_s) as link:
                at_last_frame: list[tuple[int, int]] = []  # (lost, corrupt) when each frame arrived

                def snapshot(frame: CentroidFrame) -> None:
                    at_last_frame[:] = [(link.stats.lost_messages, link.stats.corrupt_frames)]
                    if frame.frame >= n_frames - 1:
                        raise _SpanDone  # the sensor has streamed n_frames frames from frame 0

                result = StreamResult()
                try:
                    stream_frames(link, None, frame_timeout_s=frame_timeout_s, on_frame=snapshot, result=result)
                except _SpanDone:
                    pass
                # what the link counted up to the last frame (stopping the stream may lose more after it)
                reported, detected = at_last_frame[0] if at_last_frame else (0, 0)
            elapsed = time.monotonic() - t0
        finally:
            relay.close()
    frames = result.frames
    counters = [f.frame for f in frames]
    span = counters[-1] + 1 if counters else 0  # frames 0 .. the last received
    truth = _truth(sim_frames, seed, span)
    with_mag = transport != "can"  # CAN star frames carry no magnitude (protocol/can_frames.py)
    corrupt = sum(1 for f in frames if f.frame not in truth or not _same_on_the_wire(f, truth[f.frame], with_mag))
    return FaultRunResult(
        transport=transport + ("-rtu" if rtu else ""),
        frames_received=len(frames),
        frames_spanned=span,
        true_loss=span - len(set(counters)),
        reported_loss=reported,
        corrupt_accepted=corrupt,
        corrupt_detected=detected,
        elapsed_s=elapsed,
        down=down.counts(),
        up=up.counts(),
    )
