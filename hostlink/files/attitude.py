"""Attitude files (docs/file-formats.md, ``hostlink attitude --out``): one row per frame of a session."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from hostlink.files.atomic import atomic_open

#: Columns of every attitude file; C's elements row by row (b = C r).
ATTITUDE_COLUMNS = (
    ("frame", "t_utc", "n_stars", "n_used")
    + tuple(f"c{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
    + ("residual_rms_arcsec", "status")
)
#: Added when the attitudes carry a ship attitude (a site and the sensor's mounting were given).
SHIP_COLUMNS = ("ship_yaw_deg", "ship_pitch_deg", "ship_roll_deg")


def _cell(value: float) -> str:
    return "" if not math.isfinite(value) else repr(float(value))


def write_attitudes(path: str | Path, attitudes) -> None:
    """Write ATTITUDE.csv atomically from a :class:`hostlink.sky.attitude.SessionAttitudes`: frame, t_utc, n_stars,
    n_used, c11..c33, residual_rms_arcsec [arcsec, 4 decimals], status, then ship_yaw_deg, ship_pitch_deg,
    ship_roll_deg [deg] when it has a ship attitude. Unsolved values are empty cells."""
    ship = attitudes.ship_ypr_deg
    with atomic_open(path, newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ATTITUDE_COLUMNS + (SHIP_COLUMNS if ship is not None else ()))
        for k in range(attitudes.n_frames):
            rms = float(attitudes.residual_rms_arcsec[k])
            w.writerow(
                [
                    int(attitudes.frame[k]),
                    attitudes.t_utc[k],
                    int(attitudes.n_stars[k]),
                    int(attitudes.n_used[k]),
                ]
                + [_cell(v) for v in attitudes.C[k].reshape(9)]
                + ["" if not math.isfinite(rms) else f"{rms:.4f}", attitudes.status[k]]
                + ([] if ship is None else [_cell(v) for v in ship[k]])
            )
