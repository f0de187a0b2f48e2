"""The worked session's starting files, from package data, so that a user who installed the package (no repository
checkout) can follow the README's worked session: ``hostlink example DIR`` writes them.

* ``nominal.json``: what a user knows before calibrating: the 1024 x 1024 px, 12 um detector, the 70 mm design focal
  length, the principal point at the image centre and no distortion (seed 004's design);
* ``true-camera.json``: the camera the simulator looks through: seed 004's simulated camera (f 70.2262 mm, principal
  point (500, 530) px, its radial distortion in this project's convention, docs/camera-model.md);
* ``README.txt``: the commands that follow (:data:`NEXT_COMMANDS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hostlink.errors import UserError
from hostlink.files.atomic import write_text
from hostlink.files.params import load_params, save_params

#: Files written by :func:`write_example`: name in the example directory -> the package data it copies.
EXAMPLE_FILES: dict[str, str] = {
    "nominal.json": "builtin:seed004_nominal",
    "true-camera.json": "builtin:seed004_camera",
}

#: The worked session, run from the example directory (the README shows the same commands).
NEXT_COMMANDS: tuple[str, ...] = (
    "hostlink simulate --camera true-camera.json --frames 1000 --out s.csv",
    "hostlink calibrate s.csv --nominal nominal.json --out cal.json --plot plots/",
    "hostlink replay s.csv --nominal nominal.json --out onboard.json --trace trace.csv",
    "hostlink attitude s.csv --params cal.json --out attitude.csv --wcs wcs",
)

_README = """\
The worked session of startracker-companion (written by `hostlink example`).

  nominal.json      what you know before calibrating: 1024 x 1024 px detector, 12 um pixels, 70 mm design
                    focal length, principal point at the image centre (511.5, 511.5) px, no distortion
  true-camera.json  the camera the simulator looks through (f 70.2262 mm, principal point (500, 530) px,
                    radial distortion): what calibration should find

Run from this directory:

{commands}

  s.csv, s.truth.json   1000 simulated frames of the real sky (Hipparcos) with 0.05 px centroid noise, and the truth
  cal.json              batch calibration (bundle adjustment) with the 1-sigma of every parameter
  plots/                residual fields before (nominal camera) and after calibration, and the fit's convergence
  onboard.json          the sensor's own recursive estimator run over the session, frame by frame
  trace.csv             that estimator's state after every frame
  attitude.csv          one attitude per frame (b = C r, quaternion, boresight RA/Dec/roll) with the calibrated camera
  wcs/                  one FITS WCS header per frame (TAN-SIP of the calibrated camera), for astropy

Then talk to an emulated sensor (the first line `hostlink emulate` prints is its --link string):

  hostlink emulate --transport serial &
  hostlink upload cal.json --link serial:/dev/pts/N@921600
  hostlink params --link serial:/dev/pts/N@921600

`hostlink COMMAND --help` documents every option.
"""


@dataclass(frozen=True)
class ExampleFiles:
    directory: Path
    written: tuple[Path, ...]


def readme_text() -> str:
    """The example directory's README.txt."""
    return _README.format(commands="\n".join(f"  {c}" for c in NEXT_COMMANDS))


def write_example(directory: str | Path, overwrite: bool = False) -> ExampleFiles:
    """Write the worked session's starting files into ``directory`` (created if needed). Refuses (one-line
    :class:`UserError`) to replace an existing file unless ``overwrite``. The parameter files are read and validated
    from package data and written with :func:`hostlink.files.params.save_params`."""
    directory = Path(directory)
    targets = [directory / name for name in (*EXAMPLE_FILES, "README.txt")]
    existing = [p for p in targets if p.exists()]
    if existing and not overwrite:
        raise UserError(f"{existing[0]} exists (use --force to replace the example files)")
    if directory.exists() and not directory.is_dir():
        raise UserError(f"{directory}: not a directory")
    for name, source in EXAMPLE_FILES.items():
        save_params(directory / name, load_params(source))
    write_text(directory / "README.txt", readme_text())
    return ExampleFiles(directory, tuple(targets))
