"""Builds the emulated sensor from ``hostlink emulate``'s options: factory banks, estimator, frame source."""

from __future__ import annotations

from collections.abc import Callable

from hostlink.emulator.sensor import EmulatedSensor, session_frames
from hostlink.errors import UserError
from hostlink.files.params import load_params
from onboard import banks
from onboard.firmware import PRECISIONS, EstimatorBudget, Firmware, RecursiveEstimator
from onboard.params import ESTIMATE_NAMES, CameraParams, PlausibilityLimits, check_plausible
from onboard.recursive import RecursiveConfig, drift_focal_mm_per_frame_for, parse_estimate_names

DEFAULT_NOMINAL = "builtin:seed004_nominal"
DEFAULT_CAMERA = "builtin:seed004_camera"


def _tcp_port(text: str) -> int:
    if not (text.isascii() and text.isdigit() and int(text) < 65536):  # ASCII: "５０２".isdigit() too
        raise ValueError("expected a TCP port number 0..65535 (0: a free one)")
    return int(text)


#: The ``hostlink emulate --option KEY=VALUE`` settings each transport's endpoint reads: key -> (value parser, help).
#: A parser raises ValueError with what it expected.
ENDPOINT_OPTIONS: dict[str, dict[str, tuple[Callable[[str], object], str]]] = {
    "serial": {},
    "can": {},
    "modbus": {"rtu_port": (_tcp_port, "TCP port of the Modbus RTU-over-TCP server (default 0: a free one)")},
}


def parse_endpoint_options(transport: str, items: list[str]) -> dict[str, object]:
    """``--option KEY=VALUE`` items -> the endpoint's settings (``EndpointOptions.extra``), each value parsed. An item
    without ``=``, a key the transport does not read (the known ones are listed) or a bad value is a one-line
    :class:`UserError`."""
    known = ENDPOINT_OPTIONS[transport]
    extra: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UserError(f"--option {item!r}: expected KEY=VALUE")
        if key not in known:
            listed = ", ".join(known) or "none"
            raise UserError(f"--option {key}: not a setting of the {transport} emulator (known: {listed})")
        try:
            extra[key] = known[key][0](value.strip())
        except ValueError as exc:
            raise UserError(f"--option {key}={value.strip()}: {exc}") from None
    return extra


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
    precision: str = "float32",
    firmware: str = "python",
    phase_starts: tuple[int, ...] = (),
) -> EmulatedSensor:
    """Firmware with the factory set ``nominal`` in bank A, fed by ``replay`` or by the simulator; ``budget`` models
    the sensor's processor (which exposures its estimator processes; default :class:`EstimatorBudget`); ``flash``:
    the flash image file (:func:`sensor_banks`; ``power_cut_after_units``: its test hook); ``precision``: the
    sensor's arithmetic (``onboard.firmware.PRECISIONS``: "float32", or "fixed" for a sensor without an FPU);
    ``firmware``: "python" (the reference model, ``onboard.firmware``) or "c" (the C core, ``onboard/c``, built and
    run in this process: :func:`c_firmware`); ``phase_starts``: frame counters where the replay's phases begin
    (:class:`EmulatedSensor`: a restarted stream begins at the next one)."""
    from hostlink.sky.simulate import SimConfig, simulate

    nominal_params = load_params(nominal or DEFAULT_NOMINAL)
    try:
        names = parse_estimate_names(estimate_names)
    except ValueError as exc:
        raise UserError(f"--estimate: {exc}") from None
    if precision not in PRECISIONS:
        raise UserError(f"--precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    if estimator and precision == "fixed":
        from hostlink.calibration.replay import check_fixed_range

        check_fixed_range(nominal_params)
    if firmware not in FIRMWARES:
        raise UserError(f"--firmware: expected one of {', '.join(FIRMWARES)}, got {firmware!r}")
    if phase_starts and not replay:
        # the simulated source cycles forever: a restarted stream would skip exposures without end to a far start
        raise UserError("--phase-start goes with --replay (the phases of a replayed session)")
    # the focal random walk scaled to this sensor's lens (the default is the built-in 70 mm lens's)
    walk_mm = drift_focal_mm_per_frame_for(nominal_params.focal_length_mm)
    config = RecursiveConfig(centroid_noise_px=noise_px, drift_focal_mm_per_frame=walk_mm)
    if firmware == "c":
        sensor_firmware = c_firmware(
            nominal_params, flash, power_cut_after_units, budget, names if estimator else None, noise_px, precision
        )
    else:
        seam = RecursiveEstimator(names, config, precision=precision) if estimator else None
        store = sensor_banks(nominal_params, flash, power_cut_after_units, estimator and precision == "fixed")
        sensor_firmware = Firmware(store, seam, budget)
    if replay:
        from hostlink.files.session import check_on_detector, read_session

        session = read_session(replay)
        # a centroid off the sensor's detector is not one it could send (nor fit the wire's fixed point)
        check_on_detector(session, nominal_params.image_size_px, replay, nominal or DEFAULT_NOMINAL)
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
    return EmulatedSensor(sensor_firmware, _chain(first, source), phase_starts)


def sensor_banks(
    nominal: CameraParams,
    flash: str | None = None,
    power_cut_after_units: int | None = None,
    fixed_point: bool = False,
) -> banks.BankStore:
    """The sensor's parameter banks. Without ``flash``: in RAM, factory set ``nominal`` as generation 1 (lost when
    the process ends). With it: the flash image in that file (``hostlink.emulator.flash``), booted as the sensor
    boots (the last committed set, its generation and the session counter); a new or blank image first receives the
    factory set. Either way the sensor's declared design (``onboard.params.PlausibilityLimits``) is ``nominal``'s
    focal length, and a ``fixed_point`` sensor's the range of its formats. ``power_cut_after_units``:
    :class:`~hostlink.emulator.flash.FileFlash`'s test hook."""
    limits = PlausibilityLimits(design_focal_length_mm=nominal.focal_length_mm, fixed_point=fixed_point)
    identity = unit_identity(flash)  # each emulated unit its own: its sessions' nonces are its own
    if flash is None:
        return banks.factory_store(nominal, limits=limits, identity=identity)
    from hostlink.emulator.flash import FileFlash

    device = FileFlash(flash, power_cut_after_units)
    store = banks.boot(device, limits, identity)
    if store.active_record is None:
        store = banks.factory_store(nominal, flash=device, limits=limits, identity=identity)
    return store


def unit_identity(flash: str | None) -> banks.DeviceIdentity:
    """The emulated unit's identity. With ``flash`` the unit is its flash file: its uid (an MCU's unique ID, fixed in
    silicon) is derived from the file's resolved path, so a unit restarted on its flash is the same device (its
    sessions' nonces follow its persisted counter under one key) while a copy of the image elsewhere is another
    unit. In RAM, a new unit at every start. The random source is the operating system's entropy either way."""
    if flash is None:
        return banks.random_identity()
    import hashlib
    from pathlib import Path

    uid = hashlib.sha256(b"emulated unit uid\0" + str(Path(flash).resolve()).encode()).digest()[: banks.UID_BYTES]
    return banks.DeviceIdentity(uid, banks.random_identity().random32)


#: The firmwares ``hostlink emulate --firmware`` runs: the Python reference model and the C core.
FIRMWARES = ("python", "c")


def c_firmware(
    nominal: CameraParams,
    flash: str | None = None,
    power_cut_after_units: int | None = None,
    budget: EstimatorBudget | None = None,
    estimate_names: tuple[str, ...] | None = ESTIMATE_NAMES,
    noise_px: float = 0.05,
    precision: str = "float32",
):
    """The C firmware core (``hostlink.portkit.firmware_c``) over the same banks as :func:`sensor_banks`: RAM or the
    ``flash`` file, booted, the factory set ``nominal`` written first when the flash holds no set; a new device
    identity. ``estimate_names`` None: no estimator. A build without the estimator's C implementation has none
    either: READ_ESTIMATE then answers NO_ESTIMATE ("this sensor has no onboard estimator"). The estimator's focal
    random walk is scaled to ``nominal``'s focal length (``onboard.recursive.drift_focal_mm_per_frame_for``), as
    :func:`build_sensor` gives the Python firmware."""
    from hostlink.portkit.firmware_c import CFirmware

    fixed_point = precision == "fixed" and estimate_names is not None
    limits = PlausibilityLimits(design_focal_length_mm=nominal.focal_length_mm, fixed_point=fixed_point)
    check_plausible(nominal, limits)  # what factory_store checks before it writes the set
    identity = unit_identity(flash)
    if flash is None:
        device = banks.RamFlash()
    else:
        from hostlink.emulator.flash import FileFlash

        device = FileFlash(flash, power_cut_after_units)
    blank = banks.boot(device, limits, identity).active_record is None  # reads only: the same boot rules as the core
    mask = 0 if estimate_names is None else sum(1 << ESTIMATE_NAMES.index(n) for n in estimate_names)
    return CFirmware(
        device,
        identity,
        limits,
        factory=nominal if blank else None,
        budget=budget,
        estimate_mask=mask,
        precision=precision,
        centroid_noise_px=noise_px,
        drift_focal_mm_per_frame=drift_focal_mm_per_frame_for(nominal.focal_length_mm),
        with_estimator=estimate_names is not None,
    )


def _chain(first, rest):
    yield first
    yield from rest
