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
from hostlink.files.atomic import AtomicFile, cannot_write
from protocol.param_table import DISTORTION_NAMES

#: Trace columns (docs/file-formats.md requires frame, focal_length_mm, x0_px, y0_px).
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


class TraceWriter:
    """The one trace writer: rows are appended chunk by chunk as the replay goes (``append``: column name -> one
    value per frame, :data:`TRACE_COLUMNS`), into a temporary file renamed onto ``path`` by :meth:`commit`
    (:class:`hostlink.files.atomic.AtomicFile`). Memory holds one chunk, whatever the session's length. As a
    context manager: a normal exit commits; an exception removes the temporary file (a failed replay leaves no
    trace that looks finished)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.rows = 0
        self._file = AtomicFile(self.path, newline="")
        self._writer = None

    def append(self, trace: dict[str, list]) -> None:
        if self._writer is None:
            self._writer = csv.writer(self._file.open(), lineterminator="\n")
            self._write([TRACE_COLUMNS])
        columns = [[_cell(c, v) for v in trace[c]] for c in TRACE_COLUMNS]
        self._write(zip(*columns, strict=True))
        self.rows += len(trace["frame"])

    def _write(self, rows) -> None:
        try:
            self._writer.writerows(rows)
        except OSError as exc:
            raise cannot_write(self.path, exc) from None

    def commit(self) -> None:
        """Rename the finished trace onto ``path`` (a trace without frames is its header)."""
        if self._writer is None:
            self.append({c: [] for c in TRACE_COLUMNS})
        self._file.commit()

    def abandon(self) -> None:
        """Remove the temporary file; ``path`` is left as it was."""
        self._file.abandon(keep=False)

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, exc_type, exc, _tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abandon()


def write_trace(path: str | Path, trace: dict[str, list]) -> None:
    """Write the per-frame trace CSV atomically: ``trace`` maps each of :data:`TRACE_COLUMNS` to one value per
    frame (one :class:`TraceWriter` chunk)."""
    with TraceWriter(path) as writer:
        writer.append(trace)


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
