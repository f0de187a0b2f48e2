"""Attitude files (docs/file-formats.md, ``hostlink attitude --out``): one row per frame of a session."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import atomic_open
from hostlink.sky.pointing import attitude_quaternion, boresight_radec_roll

#: The direction cosine matrix's columns of an attitude file, row by row (b = C r).
MATRIX_COLUMNS = tuple(f"c{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
#: Columns of every attitude file; C's elements row by row (b = C r).
ATTITUDE_COLUMNS = ("frame", "t_utc", "n_stars", "n_used") + MATRIX_COLUMNS + ("residual_rms_arcsec", "status")
#: The attitude in other forms, from C (:mod:`hostlink.sky.pointing`): the quaternion, scalar first, carrying the
#: reference axes onto the sensor axes; the boresight (+z) right ascension and declination [deg] in the reference
#: frame; the roll [deg] from the image's up (-y) to the projected celestial north, toward +x.
POINTING_COLUMNS = ("q0", "q1", "q2", "q3", "boresight_ra_deg", "boresight_dec_deg", "roll_deg")
#: Added when the attitudes carry a ship attitude (a site and the sensor's mounting were given).
SHIP_COLUMNS = ("ship_yaw_deg", "ship_pitch_deg", "ship_roll_deg")


def _cell(value: float) -> str:
    return "" if not math.isfinite(value) else repr(float(value))


def attitude_columns(attitudes) -> tuple[str, ...]:
    """The columns of ``attitudes``' file: :data:`ATTITUDE_COLUMNS`, :data:`POINTING_COLUMNS`, and
    :data:`SHIP_COLUMNS` when it has a ship attitude."""
    return ATTITUDE_COLUMNS + POINTING_COLUMNS + (SHIP_COLUMNS if attitudes.ship_ypr_deg is not None else ())


def attitude_rows(attitudes) -> Iterator[list]:
    """One list of values per frame, in :func:`attitude_columns` order: ints, the time text, floats (NaN where
    unsolved; the residual RMS rounded to 4 decimals of an arcsecond) and the status text. The one source of the
    file's rows (:func:`write_attitudes`) and of ``hostlink attitude --json`` (:func:`attitude_records`)."""
    ship = attitudes.ship_ypr_deg
    quaternions = attitude_quaternion(attitudes.C)
    for k in range(attitudes.n_frames):
        rms = float(attitudes.residual_rms_arcsec[k])
        solved = bool(np.all(np.isfinite(attitudes.C[k])))
        pointing = boresight_radec_roll(attitudes.C[k]) if solved else (math.nan,) * 3
        yield (
            [int(attitudes.frame[k]), attitudes.t_utc[k], int(attitudes.n_stars[k]), int(attitudes.n_used[k])]
            + [float(v) for v in attitudes.C[k].reshape(9)]
            + [round(rms, 4) if math.isfinite(rms) else math.nan, attitudes.status[k]]
            + [float(v) for v in quaternions[k]]
            + [float(v) for v in pointing]
            + ([] if ship is None else [float(v) for v in ship[k]])
        )


def attitude_records(attitudes) -> list[dict]:
    """The file's rows as JSON objects keyed by its column names (NaN as None: JSON null)."""
    names = attitude_columns(attitudes)
    return [
        {n: None if isinstance(v, float) and not math.isfinite(v) else v for n, v in zip(names, row, strict=True)}
        for row in attitude_rows(attitudes)
    ]


def write_attitudes(path: str | Path, attitudes) -> None:
    """Write ATTITUDE.csv atomically from a :class:`hostlink.sky.attitude.SessionAttitudes`: frame, t_utc, n_stars,
    n_used, c11..c33, residual_rms_arcsec [arcsec, 4 decimals], status, q0..q3, boresight_ra_deg,
    boresight_dec_deg, roll_deg (:data:`POINTING_COLUMNS`), then ship_yaw_deg, ship_pitch_deg, ship_roll_deg [deg]
    when it has a ship attitude. Unsolved values are empty cells."""
    rms_column = ATTITUDE_COLUMNS.index("residual_rms_arcsec")
    with atomic_open(path, newline="") as fh:
        w = csv.writer(fh)
        w.writerow(attitude_columns(attitudes))
        for row in attitude_rows(attitudes):
            cells = [_cell(v) if isinstance(v, float) else v for v in row]
            rms = row[rms_column]
            cells[rms_column] = f"{rms:.4f}" if math.isfinite(rms) else ""
            w.writerow(cells)


def read_attitude_matrices(path: str | Path) -> np.ndarray:
    """The attitudes C (b = C r) of a CSV with columns c11..c33, one row a frame (``hostlink simulate --attitudes``;
    an attitude file of ``hostlink attitude`` is one), as an (n, 3, 3) float64 array. Raises a one-line
    :class:`UserError` for a missing file, a missing column or a value that is not a number."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            reader = csv.DictReader(handle)
            missing = [n for n in MATRIX_COLUMNS if n not in (reader.fieldnames or [])]
            if missing:
                raise UserError(f"{path}: missing column(s) {', '.join(missing)}")
            rows = [[float(r[n]) for n in MATRIX_COLUMNS] for r in reader]
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, csv.Error, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read attitudes ({exc})") from None
    except (TypeError, ValueError):
        raise UserError(f"{path}: every c11..c33 value must be a number") from None
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3, 3)
