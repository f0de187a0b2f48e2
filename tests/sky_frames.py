"""Shared by the tests that render the real sky (Hipparcos) through a known camera: the camera and the attitude that
points it."""

from __future__ import annotations

import numpy as np

from onboard.camera import radec_to_unit
from onboard.params import CameraParams

#: 1024 x 768 px at f = 25 mm, 6.9 um: 16 x 12 deg, 57" per pixel.
CAMERA = CameraParams(
    focal_length_mm=25.0, pixel_pitch_um=6.9, principal_point_px=(511.5, 383.5), image_size_px=(1024, 768)
)


def attitude_toward(ra_deg: float, dec_deg: float) -> np.ndarray:
    """Rows: the camera's x, y, z axes in J2000 (z the boresight at (ra, dec), x in the equator's plane: roll 0)."""
    z = radec_to_unit(np.radians([ra_deg]), np.radians([dec_deg]))[0]
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])
