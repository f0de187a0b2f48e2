"""Builds the emulated sensor from ``hostlink emulate``'s options: factory banks, estimator, frame source."""

from __future__ import annotations

from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.errors import UserError
from hostlink.files.params import load_params
from onboard import banks
from onboard.firmware import EstimatorBudget, Firmware, RecursiveEstimator
from onboard.params import CameraParams, PlausibilityLimits
from onboard.recursive import RecursiveConfig, parse_estimate_names

DEFAULT_NOMINAL = "builtin:seed004_nominal"
DEFAULT_CAMERA = "builtin:seed004_camera"


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
    flash: str | None = None,
    power_cut_after_units: int | None = None,
) -> EmulatedSensor:
    """Firmware with the factory set ``nominal`` in bank A, fed by ``replay`` or by the simulator; ``budget`` models
    the sensor's processor (which exposures its estimator processes; default :class:`EstimatorBudget`); ``flash``:
    the flash image file (:func:`sensor_banks`; ``power_cut_after_units``: its test hook)."""
    from hostlink.sky.simulate import SimConfig, simulate

    nominal_params = load_params(nominal or DEFAULT_NOMINAL)
    try:
        names = parse_estimate_names(estimate_names)
    except ValueError as exc:
        raise UserError(f"--estimate: {exc}") from None
    seam = RecursiveEstimator(names, RecursiveConfig(centroid_noise_px=noise_px)) if estimator else None
    firmware = Firmware(sensor_banks(nominal_params, flash, power_cut_after_units), seam, budget)
    if replay:
        from hostlink.files.session import read_session

        session = read_session(replay)
        cycle = False
    else:
        sim = simulate(
            SimConfig(camera=load_params(camera or DEFAULT_CAMERA), frames=sim_frames, noise_px=noise_px, seed=seed)
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


def sensor_banks(
    nominal: CameraParams, flash: str | None = None, power_cut_after_units: int | None = None
) -> banks.BankStore:
    """The sensor's parameter banks. Without ``flash``: in RAM, factory set ``nominal`` as generation 1 (lost when
    the process ends). With it: the flash image in that file (``hostlink.emulator.flash``), booted as the sensor
    boots (the last committed set, its generation and the session counter); a new or blank image first receives the
    factory set. Either way the sensor's declared design (``onboard.params.PlausibilityLimits``) is ``nominal``'s
    focal length. ``power_cut_after_units``: :class:`~hostlink.emulator.flash.FileFlash`'s test hook."""
    limits = PlausibilityLimits(design_focal_length_mm=nominal.focal_length_mm)
    if flash is None:
        return banks.factory_store(nominal, limits=limits)
    from hostlink.emulator.flash import FileFlash

    device = FileFlash(flash, power_cut_after_units)
    store = banks.boot(device, limits)
    if store.active_record is None:
        store = banks.factory_store(nominal, flash=device, limits=limits)
    return store


def _chain(first, rest):
    yield first
    yield from rest
