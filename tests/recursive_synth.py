"""Synthetic frames for the recursive-estimator tests: the generators live in the package
(``hostlink.calibration.synthetic``, the bounds in ``hostlink.calibration.crb``, both exposed through
``hostlink.api``); this module keeps the tests' short names."""

from __future__ import annotations

import numpy as np

from hostlink.calibration.crb import interstar_batch_ml as batch_ml  # noqa: F401
from hostlink.calibration.crb import interstar_information
from hostlink.calibration.synthetic import (  # noqa: F401
    Frame,
    make_frame,
    make_frames,
    seed004_paper_start,
    seed004_true_camera,
    sky_frames,
    synth_frames,
)
from onboard.params import CameraParams

SEED004_TRUE = seed004_true_camera()
SEED004_PAPER_START = seed004_paper_start()


def crb_information(camera: CameraParams, frames, noise_px: float, idx: np.ndarray) -> np.ndarray:
    """:func:`hostlink.calibration.crb.interstar_information` over the parameters ``idx``."""
    return interstar_information(camera, frames, noise_px, idx)
