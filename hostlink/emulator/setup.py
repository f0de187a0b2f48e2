"""Builds the emulated sensor from ``hostlink emulate``'s options: factory banks, estimator, frame source."""

from __future__ import annotations

from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.errors import UserError
from hostlink.files.params import load_params
from onboard import banks
from onboard.firmware import EstimatorBudget, Firmware, RecursiveEstimator
from onboard.recursive import RecursiveConfig, parse_estimate_names

DEFAULT_NOMINAL = "seed004_nominal.json"
DEFAULT_CAMERA = "seed004_camera.json"


def build_sensor(
    replay: str | None = None,
    nominal: str | None = None,
    camera: str | None = None,
    sim_frames: int = 500,
    noise_px: float = 0.05,
    seed: int = 0,
    estimator: bool = True,
    estimate_names: str | None = None,
    budget: EstimatorBudget | None = None,
) -> EmulatedSensor:
    """Firmware with the factory set ``nominal`` in bank A, fed by ``replay`` or by the simulator; ``budget`` models
    the sensor's processor (which exposures its estimator processes; default :class:`EstimatorBudget`)."""
    from hostlink.sky.simulate import SimConfig, data_file, simulate

    nominal_params = load_params(nominal or data_file(DEFAULT_NOMINAL))
    try:
        names = parse_estimate_names(estimate_names)
    except ValueError as exc:
        raise UserError(f"--estimate: {exc}") from None
    seam = RecursiveEstimator(names, RecursiveConfig(centroid_noise_px=noise_px)) if estimator else None
    firmware = Firmware(banks.factory_store(nominal_params), seam, budget)
    if replay:
        from hostlink.files.session import read_session

        session = read_session(replay)
        cycle = False
    else:
        sim = simulate(
            SimConfig(
                camera=load_params(camera or data_file(DEFAULT_CAMERA)), frames=sim_frames, noise_px=noise_px, seed=seed
            )
        )
        session, cycle = sim.session, True
    try:
        source = session_frames(session, cycle=cycle)
        first = next(source, None)
    except ValueError as exc:
        raise UserError(f"{replay or 'simulated session'}: {exc}") from None
    if first is None:
        raise UserError(f"{replay}: the session has no frames")
    return EmulatedSensor(firmware, _chain(first, source))


def _chain(first, rest):
    yield first
    yield from rest
