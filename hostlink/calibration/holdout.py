"""Held-out stars: judge a calibrated camera on stars that were not in its fit.

A calibration's own residual flatters it (the fit absorbed part of the noise, and a model with more parameters
absorbs more). The honest figure, and the one to compare two calibrations of the same images by, is the residual of
stars left out of both fits. Frames are held out whole (k-fold over the frames), because a plate solver's own
calibration takes whole solved frames:

1. :func:`hold_out_frames` marks the identified stars of every ``folds``-th frame (fold ``fold``);
2. each camera is fitted without those frames;
3. :func:`held_out_residuals_rad` judges each held-out star alone: the attitude of its frame is solved from the
   frame's other stars (Wahba's problem, ``onboard.attitude.attitude_from_vectors``, through the camera under test),
   so neither the camera nor the attitude saw the star; the residual is the angle between the star's measured
   direction and its reference direction rotated into the sensor frame.

The camera enters only as a function from pixels to unit vectors, so a camera from another tool (an established
plate solver's own calibration) is judged by exactly the same rule.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hostlink.files.session import Session
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad

#: pixels (x_px, y_px) -> sensor-frame unit vectors (N, 3)
PixelsToUnit = Callable[[np.ndarray, np.ndarray], np.ndarray]


def hold_out_frames(session: Session, usable: np.ndarray, folds: int, fold: int) -> np.ndarray:
    """(N,) bool: the ``usable`` rows of the frames with identified stars whose rank (in file order) is ``fold``
    modulo ``folds``."""
    if folds < 2 or not 0 <= fold < folds:
        raise ValueError(f"folds must be >= 2 and 0 <= fold < folds, got folds={folds}, fold={fold}")
    held = np.zeros(len(session), dtype=bool)
    frames = [rows for rows in session.frame_slices() if usable[rows].any()]
    for rows in frames[fold::folds]:
        held[rows] = usable[rows]
    return held


def held_out_residuals_rad(
    session: Session, to_unit: PixelsToUnit, r: np.ndarray, usable: np.ndarray, held: np.ndarray
) -> np.ndarray:
    """(N,) float64: for every ``held`` row, the angle [rad] between its direction through ``to_unit`` and its
    reference ``r`` (N, 3) rotated by the attitude solved from the other ``usable`` rows of its frame (leave one
    out); NaN elsewhere and where fewer than 2 other stars (or only parallel ones) leave the attitude undetermined."""
    out = np.full(len(session), np.nan)
    b = to_unit(session.x_px, session.y_px)
    for rows in session.frame_slices():
        index = np.arange(rows.start, rows.stop)
        stars = index[usable[rows]]
        for row in index[held[rows]]:
            others = stars[stars != row]
            if others.size < 2:
                continue
            try:
                c = attitude_from_vectors(b[others], r[others])
            except DegenerateGeometry:
                continue
            out[row] = residuals_rad(b[row : row + 1], r[row : row + 1], c)[0]
    return out
