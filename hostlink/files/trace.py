"""Replay traces (docs/file-formats.md, ``hostlink replay --trace TRACE.csv``): the one reader and the one writer.

One row per frame: the onboard estimator's state after that frame (``hostlink.calibration.replay`` fills the
columns). Focal length and its sigma are written with 9 decimals of a millimetre (1 pm), other floats with 9
significant digits (beyond float32's 7).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import atomic_open
from protocol.param_table import DISTORTION_NAMES

#: Trace columns (INTERFACES.md requires frame, focal_length_mm, x0_px, y0_px).
TRACE_COLUMNS = (
    "frame",
    "t_utc",
    "focal_length_mm",
    "x0_px",
    "y0_px",
    *DISTORTION_NAMES,
    "sigma_f_mm",
    "sigma_x0_px",
    "sigma_y0_px",
    "n_stars",
    "n_used",
    "n_rejected_stars",
    "n_pairs",
    "iterations",
    "nis",
    "drift_on",
    "skipped",
)
#: Columns holding whole numbers, and text; every other column is a float.
INTEGER_COLUMNS = ("frame", "n_stars", "n_used", "n_rejected_stars", "n_pairs", "iterations", "drift_on")
TEXT_COLUMNS = ("t_utc", "skipped")
#: Columns written with 9 decimals (millimetres: 1 pm), not 9 significant digits.
_MM_COLUMNS = ("focal_length_mm", "sigma_f_mm")


def _cell(name: str, value) -> str:
    if name in INTEGER_COLUMNS:
        return str(int(value))
    if name in TEXT_COLUMNS:
        return str(value)
    if name in _MM_COLUMNS:
        return "%.9f" % value
    return "%.9g" % value


def write_trace(path: str | Path, trace: dict[str, list]) -> None:
    """Write the per-frame trace CSV atomically: ``trace`` maps each of :data:`TRACE_COLUMNS` to one value per
    frame."""
    n = len(trace["frame"])
    with atomic_open(path, newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(TRACE_COLUMNS)
        for k in range(n):
            writer.writerow([_cell(c, trace[c][k]) for c in TRACE_COLUMNS])


def read_trace(path: str | Path) -> dict[str, np.ndarray]:
    """A trace CSV -> column name -> one value per frame: int64 for :data:`INTEGER_COLUMNS`, text (object) for
    :data:`TEXT_COLUMNS`, float64 otherwise. Columns it does not know are kept as text. A missing or malformed file
    is a one-line UserError."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.reader(handle))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UserError(f"{path}: not a readable trace file ({exc})") from None
    if not rows or "frame" not in rows[0]:
        raise UserError(f"{path}: not a trace file (no header with a frame column)")
    header, body = rows[0], rows[1:]
    out: dict[str, np.ndarray] = {}
    for j, name in enumerate(header):
        cells = [row[j] if j < len(row) else "" for row in body]
        try:
            if name in INTEGER_COLUMNS:
                out[name] = np.array([int(c) for c in cells], dtype=np.int64)
            elif name in TRACE_COLUMNS and name not in TEXT_COLUMNS:
                out[name] = np.array([float(c) for c in cells], dtype=np.float64)
            else:
                out[name] = np.array(cells, dtype=object)
        except ValueError as exc:
            raise UserError(f"{path}: column {name}: {exc}") from None
    return out
