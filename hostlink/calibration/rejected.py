"""The identified stars a calibration did not use: each with its reason and residual (the ``--rejected`` CSV,
docs/file-formats.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.frames import wahba_attitudes
from hostlink.calibration.model import angle_arcsec, rotate
from onboard.camera import pixels_to_unit

#: Reasons of :class:`RejectedStars`, in the order a star meets them.
REASON_UNKNOWN_ID = "unknown star_id (not in the Hipparcos catalogue)"
REASON_FEW_IN_FRAME = "frame has fewer than 3 identified stars with a reference direction"
REASON_VOTING = "interstar voting (its angles to most stars of its frame disagree with the catalogue)"
REASON_GATING = "residual gating (beyond 5 robust sigmas after the fit)"
REASON_FRAME_LEFT = "frame left with fewer than 3 stars after the rejections"


@dataclass(frozen=True)
class RejectedStars:
    """Every identified star of a session that the calibration did not use, one entry per star, in row order.

    row: (n,) session row (0 = first data row; the file line is row + 2); frame, star_id: from the session;
    reason: one of the ``REASON_*`` texts; residual_arcsec: angle between the star's measured direction through the
    calibrated camera and its reference rotated by its frame's attitude (NaN where there is none)."""

    row: np.ndarray
    frame: np.ndarray
    star_id: np.ndarray
    reason: np.ndarray
    residual_arcsec: np.ndarray

    def __len__(self) -> int:
        return int(self.row.shape[0])

    def counts(self) -> dict[str, int]:
        """Number of rejected stars per reason."""
        names, n = np.unique(self.reason.astype(str), return_counts=True)
        return {str(a): int(b) for a, b in zip(names, n, strict=True)}


def rejected_residuals_arcsec(data: CalibrationData, theta: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(N,) angle [arcsec] of every star of ``data`` from its reference rotated by its frame's attitude, the
    least-squares attitude (Markley's rotation) fitted to the ``used`` stars of the frame through the camera
    ``theta``, or to all its stars when none was used."""
    b = pixels_to_unit(data.x_px, data.y_px, theta)
    fidx = data.frame_index()
    any_used = np.bincount(fidx, weights=used, minlength=data.n_frames) > 0
    weights = np.where(any_used[fidx], used.astype(float), 1.0)
    att = wahba_attitudes(b, data.r, data.frame_starts, weights)
    return angle_arcsec(b, rotate(att[fidx], data.r))


def rejected_stars(session, references, data_in: CalibrationData, outcome) -> RejectedStars:
    """Every identified row of ``session`` the calibration ``outcome`` did not use, with its reason
    (``REASON_*``) and residual: unknown star ids (``references``), stars of frames with fewer than three usable,
    and of the calibration's input ``data_in`` those rejected by voting, by gating or with their frame."""
    n = len(session)
    reason = np.full(n, "", dtype=object)
    residual = np.full(n, np.nan)
    reason[references.unknown_rows] = REASON_UNKNOWN_ID
    usable = np.flatnonzero(references.usable)
    reason[np.setdiff1d(usable, data_in.source_rows())] = REASON_FEW_IN_FRAME
    rows_in = data_in.source_rows()
    used = np.isin(rows_in, outcome.data.source_rows())
    residual[rows_in] = rejected_residuals_arcsec(data_in, outcome.theta, used)
    left = ~used
    if outcome.voted_out is not None:
        reason[rows_in[outcome.voted_out]] = REASON_VOTING
        left &= ~outcome.voted_out
    if outcome.gated is not None:
        reason[rows_in[outcome.gated]] = REASON_GATING
        left &= ~outcome.gated
    reason[rows_in[left]] = REASON_FRAME_LEFT
    rows = np.flatnonzero(reason != "")
    return RejectedStars(
        row=rows,
        frame=session.frame[rows],
        star_id=session.star_id[rows],
        reason=reason[rows],
        residual_arcsec=residual[rows],
    )


def write_rejected(path, rejected: RejectedStars) -> None:
    """The ``--rejected`` CSV (docs/file-formats.md): row, line, frame, star_id, reason, residual_arcsec (empty
    where there is none), through the one atomic writer (``hostlink.files.atomic``)."""
    import csv

    from hostlink.files.atomic import atomic_open

    with atomic_open(path, newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["row", "line", "frame", "star_id", "reason", "residual_arcsec"])
        for k in range(len(rejected)):
            res = rejected.residual_arcsec[k]
            row = int(rejected.row[k])
            w.writerow(
                [
                    row,
                    row + 2,
                    int(rejected.frame[k]),
                    int(rejected.star_id[k]),
                    rejected.reason[k],
                    f"{res:.3f}" if math.isfinite(res) else "",
                ]
            )
