"""Test helpers for in-process stream tests (the emulated sensor's stream start, loss counting, phase starts): a
one-star centroid frame per frame counter and the 70 mm nominal camera those tests' Python firmware is built on."""

from __future__ import annotations

import numpy as np

from onboard.params import CameraParams
from protocol import messages as m

#: The nominal camera of the in-process sensors (any plausible set: these tests look at frame counters only).
NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)
#: The first frame's time [us since 1970]: November 2023, any valid instant.
T0_US = 1_700_000_000_000_000


def one_star_frame(k: int, period_us: int = 100_000) -> m.CentroidFrame:
    """Frame counter ``k``, taken ``k`` periods after T0_US: one star (id k + 1) at (k + 0.5, 2.25) px, magnitude 3,
    so every frame is told apart by its contents as well as its counter."""
    return m.CentroidFrame(
        frame=k,
        t_us=T0_US + period_us * k,
        star_id=np.array([k + 1], np.uint32),
        x_px=np.array([k + 0.5]),
        y_px=np.array([2.25]),
        mag=np.array([3.0]),
    )
