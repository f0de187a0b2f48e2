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
from dataclasses import dataclass

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.params import CameraParams
from onboard.site import Site, Weather

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


@dataclass(frozen=True)
class CrossValidation:
    """The held-out figure of a calibration (module docstring): ``folds`` fits, each without one fold of the frames,
    each judged on the stars of its left-out frames.

    rms_px: RMS over every judged star of the held-out angle [px, at each fold's focal length]; the figure to compare
    two calibrations by. fit_rms_px: the in-fit residual RMS of the same folds' fits [px], for contrast (a model that
    flatters itself shows fit_rms_px well below rms_px). focal_length_mm: each fold's fitted focal length [mm] (their
    spread shows how much one fold's frames move the camera)."""

    folds: int
    n_stars: int
    n_frames: int
    rms_px: float
    median_px: float
    fit_rms_px: float
    per_fold_rms_px: tuple[float, ...]
    focal_length_mm: tuple[float, ...]

    def as_dict(self) -> dict:
        return {
            "folds": self.folds,
            "stars": self.n_stars,
            "frames": self.n_frames,
            "rms_px": self.rms_px,
            "median_px": self.median_px,
            "fit_rms_px": self.fit_rms_px,
            "per_fold_rms_px": list(self.per_fold_rms_px),
            "focal_length_mm": list(self.focal_length_mm),
        }


def cross_validate(
    session: Session,
    nominal: CameraParams,
    folds: int = 3,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    **calibrate_options: object,
) -> CrossValidation:
    """k-fold held-out judgement of :func:`hostlink.calibration.run.calibrate_session` on ``session`` from
    ``nominal`` (a :class:`onboard.params.CameraParams`; ``site``, ``weather``, ``dut1_s`` and ``calibrate_options``
    as for ``calibrate_session``): each fold's frames (:func:`hold_out_frames`) are left out of one fit and judged
    by :func:`held_out_residuals_rad` through that fit's camera. Raises :class:`UserError` (one line) when a fold's
    fit fails or fewer than 3 frames have identified stars."""
    from hostlink.calibration.data import calibration_data_from_session
    from hostlink.calibration.run import calibrate_session
    from onboard.camera import pixels_to_unit

    if folds < 2:
        raise UserError(f"--hold-out {folds}: expected at least 2 folds")
    _, references = calibration_data_from_session(session, site, weather, dut1_s)
    r, usable = references.r, references.usable
    n_frames = sum(1 for rows in session.frame_slices() if usable[rows].any())
    if n_frames < folds:
        raise UserError(f"--hold-out {folds}: only {n_frames} frames have identified stars; need one per fold")
    judged: list[np.ndarray] = []
    per_fold: list[float] = []
    fit_rms: list[float] = []
    focal_mm: list[float] = []
    for fold in range(folds):
        held = hold_out_frames(session, usable, folds, fold)
        try:
            outcome, _ = calibrate_session(
                session.select(~held), nominal, site=site, weather=weather, dut1_s=dut1_s, **calibrate_options
            )
        except UserError as exc:
            raise UserError(f"held-out fold {fold + 1} of {folds}: {exc}") from None
        theta = outcome.params.model_vector()
        res_rad = held_out_residuals_rad(session, lambda x, y, t=theta: pixels_to_unit(x, y, t), r, usable, held)
        res_px = res_rad[np.isfinite(res_rad)] * float(theta[0])
        judged.append(res_px)
        per_fold.append(float(np.sqrt(np.mean(res_px**2))) if res_px.size else float("nan"))
        fit_rms.append(float(outcome.after["rms_px"]))
        focal_mm.append(float(outcome.params.focal_length_mm))
    every = np.concatenate(judged)
    if every.size == 0:
        raise UserError("held-out judgement: no held-out star has two other stars in its frame to fix its attitude")
    return CrossValidation(
        folds=folds,
        n_stars=int(every.size),
        n_frames=n_frames,
        rms_px=float(np.sqrt(np.mean(every**2))),
        median_px=float(np.median(every)),
        fit_rms_px=float(np.sqrt(np.mean(np.square(fit_rms)))),
        per_fold_rms_px=tuple(per_fold),
        focal_length_mm=tuple(focal_mm),
    )
