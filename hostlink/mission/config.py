"""What a bench run is given: the sensor's true camera, its nominal one, the two phases and the link (pure data)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from hostlink.errors import UserError
from hostlink.files.params import load_params
from onboard.params import CameraParams, Distortion
from onboard.site import Site, Weather

#: The embedded default "true" camera: seed 004's camera (Table 1) after a launch shock: the principal point and
#: focal length moved, and small decentering and thin-prism terms appeared beside the radial distortion. Every term
#: is a few tenths of a pixel at the corner, the regime where calibration matters at the 0.05 px noise level.
BENCH_TRUE_CAMERA = CameraParams(
    focal_length_mm=70.2262,
    pixel_pitch_um=12.0,
    principal_point_px=(500.0, 530.0),
    image_size_px=(1024, 1024),
    distortion=Distortion(k1=-2.0e-10, k2=3.5e-15, p1=3.0e-7, p2=-2.0e-7, s1=1.5e-7, s2=-1.0e-7),
)
#: The built-in camera's design values (package data): the nominal of :data:`BENCH_TRUE_CAMERA`.
BENCH_NOMINAL = "builtin:seed004_nominal"
#: The default thermal drift amplitude: 6 um on the built-in 70 mm lens (8.6e-5 of its focal length), the same
#: fraction of any other lens's nominal focal length, since a lens's thermal focal change is CTE x f x dT.
BENCH_DRIFT_UM = 6.0
BENCH_DRIFT_DESIGN_FOCAL_MM = 70.0


@dataclass
class BenchConfig:
    out_dir: Path = Path("bench-report")
    transport: str = "serial"
    cal_frames: int = 600
    drift_frames: int = 3000
    #: exposures the sensor's replay holds beyond the two phases (None: :func:`spare_frames` decides): a sensor keeps
    #: taking exposures until the host's "stop streaming" reaches it, so the frames in flight then are consumed
    #: between the phases, as are frames lost on the link; the spare frames keep the drift phase at its full length
    spare_frames: int | None = None
    noise_px: float = 0.05
    misid_fraction: float = 0.0
    #: drift amplitude [um]; None: :func:`drift_amplitude_um` scales the default to the lens
    drift_um: float | None = None
    drift_period_frames: float = 3000.0
    seed: int = 1
    camera: CameraParams = field(default_factory=lambda: BENCH_TRUE_CAMERA)
    #: the sensor's factory parameters; None: :func:`bench_nominal` decides
    nominal: CameraParams | None = None
    site: Site | None = None
    weather: Weather | None = None
    maglim: float = 6.0  # faintest Hipparcos magnitude simulated (SimConfig.maglim)
    min_stars: int = 10  # fewest stars per frame (SimConfig.min_stars)
    max_stars: int = 30  # most stars per frame, brightest kept (SimConfig.max_stars)
    poll_every_frames: int = 25
    #: the sensor's arithmetic (``onboard.firmware.PRECISIONS``): "float32" (an FPU) or "fixed" (no FPU)
    precision: str = "float32"
    #: the emulated sensor's firmware (``hostlink emulate --firmware``): "python" (the reference model) or "c" (the
    #: C core, onboard/c)
    firmware: str = "python"
    #: how long the host waits for the emulated sensor's reply or next frame [s]: longer than a link's default 2 s,
    #: since the sensor is a process on the same machine, which a loaded machine can stall for seconds (the bench
    #: measures the mission, not the machine's scheduling)
    link_timeout_s: float = 10.0
    #: further ``hostlink emulate`` options for the sensor
    emulator_args: tuple[str, ...] = ()
    t0_iso: str = "2026-03-14T02:10:00.000Z"


def design_nominal(camera: CameraParams) -> CameraParams:
    """What a user knows of a camera before calibrating it (docs/file-formats.md, nominal file): its design focal
    length, pitch and image size, the principal point at the image centre ((W - 1) / 2, (H - 1) / 2 px, pixel
    centres at integers) and no distortion."""
    width, height = camera.image_size_px
    return replace(camera, principal_point_px=((width - 1) / 2.0, (height - 1) / 2.0), distortion=Distortion())


def bench_nominal(cfg: BenchConfig) -> CameraParams:
    """The sensor's factory parameters for this run: ``cfg.nominal`` if given (it must describe the same detector as
    ``cfg.camera``), the built-in design values for the built-in camera, else the camera's :func:`design_nominal`.
    A mismatched detector is a one-line UserError."""
    nominal, camera = cfg.nominal, cfg.camera
    if nominal is None:
        return load_params(BENCH_NOMINAL) if camera == BENCH_TRUE_CAMERA else design_nominal(camera)
    if nominal.image_size_px != camera.image_size_px or nominal.pixel_pitch_um != camera.pixel_pitch_um:
        raise UserError("--nominal and --camera must describe the same detector (image size and pixel pitch)")
    return nominal


def drift_amplitude_um(cfg: BenchConfig) -> float:
    """The drift phase's focal drift amplitude [um]: ``cfg.drift_um`` if given, else :data:`BENCH_DRIFT_UM` x the
    nominal focal length / :data:`BENCH_DRIFT_DESIGN_FOCAL_MM` (6 um for the built-in 70 mm camera, 1.37 um for a
    16 mm lens: the same relative drift)."""
    if cfg.drift_um is not None:
        return cfg.drift_um
    return BENCH_DRIFT_UM * (bench_nominal(cfg).focal_length_mm / BENCH_DRIFT_DESIGN_FOCAL_MM)


def spare_frames(cfg: BenchConfig) -> int:
    """Frames the sensor's replay holds beyond each phase: ``cfg.spare_frames``, or max(256, 2 cal_frames).

    They pay for the frames the sensor takes that never count for a phase: after the calibration phase, those in
    flight when the host stops its stream (dropped when the drift stream starts; the emulated sensor's next stream
    begins at the drift phase's first frame, :func:`drift_first_frame`, whatever it took meanwhile); after the drift
    phase, those lost on the link. The frames in
    flight are the host's backlog: the emulated sensor exposes as fast as its link carries frames, and a host that
    reads at a fraction q of that rate is cal_frames (1/q - 1) frames behind when it has its cal_frames (on CAN the
    host's receive queue holds them all: nothing is lost, they are late). 2 cal_frames spare frames cover q >= 1/3; 256
    cover a host that keeps up. A run that still runs out says so and fails
    (``hostlink.mission.summary.incomplete_reason``)."""
    return int(cfg.spare_frames) if cfg.spare_frames is not None else max(256, 2 * int(cfg.cal_frames))


def drift_first_frame(cfg: BenchConfig) -> int:
    """The frame counter of the drift phase's first exposure in the sensor's replay: after the calibration phase and
    its spare frames (static camera), so the exposures the sensor takes while the host stops the calibration stream
    come out of the spare frames and the drift phase, its truth and its tracking score begin at the same exposure
    however many were in flight (the emulated sensor's ``--phase-start``)."""
    return int(cfg.cal_frames) + spare_frames(cfg)
