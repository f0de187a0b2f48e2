"""Simulation truth files (docs/file-formats.md, ``SESSION.truth.json``): the one reader and the one writer.

``hostlink simulate --out S.csv`` writes ``S.truth.json`` beside the session: the true camera, the simulation's
setup and the per-frame attitude C (b = C r) and focal length, as compact JSON (floats at full precision).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import cannot_write, file_path, write_json
from onboard.params import ParameterError, params_from_dict

TRUTH_FORMAT = "startracker-companion simulation truth"
TRUTH_VERSION = 1
#: Per-frame or per-row integer lists of a truth file (numpy int64 arrays once read).
_ROW_LISTS = ("misidentified_rows", "misidentified_true_star_id", "false_rows")


#: The truth's keys that grow with the session, in the order they are written (after every other key).
TRUTH_PER_FRAME_KEYS = (
    "attitude",
    "focal_length_mm",
    "real_stars_per_frame",
    "misidentified_rows",
    "misidentified_true_star_id",
    "false_rows",
)


def truth_path_for(session_path: str | Path) -> Path:
    """``SESSION.csv`` -> ``SESSION.truth.json`` (beside it)."""
    p = file_path(session_path)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    return p.with_name(stem + ".truth.json")


def write_truth(path: str | Path, truth: dict) -> None:
    """Write the truth JSON atomically (compact, floats at full precision); an unwritable path is a one-line
    UserError."""
    write_json(path, truth, indent=None)


def read_truth(path: str | Path) -> dict:
    """Read a truth JSON; per-frame arrays become numpy arrays: ``attitude`` (F, 3, 3), ``focal_length_mm`` (F,),
    row lists as int64; ``camera`` becomes ``camera_params`` (a validated CameraParams) as well. A missing or
    malformed file is a one-line UserError."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad UTF-8, JSON or a too-long integer
        raise UserError(f"{path}: not a readable truth file ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != TRUTH_FORMAT:
        raise UserError(f"{path}: not a simulation truth file")
    try:
        data["attitude"] = np.asarray(data["attitude"], dtype=np.float64).reshape(-1, 3, 3)
        data["focal_length_mm"] = np.asarray(data["focal_length_mm"], dtype=np.float64)
        for key in _ROW_LISTS:
            data[key] = np.asarray(data[key], dtype=np.int64)
        data["camera_params"] = params_from_dict(data["camera"])
    except KeyError as exc:
        raise UserError(f"{path}: truth file without {exc.args[0]!r}") from None
    except ParameterError as exc:
        raise UserError(f"{path}: camera.{exc}") from None
    except (TypeError, ValueError) as exc:
        raise UserError(f"{path}: malformed truth file ({exc})") from None
    return data


class TruthWriter:
    """The truth JSON of a session simulated chunk by chunk (``hostlink simulate``): the same file as
    :func:`write_truth` of the whole dict, written in memory bounded by one chunk. ``header`` holds every key that
    does not grow with the session; each :meth:`append` adds a chunk's values of the ``per_frame`` keys (numpy
    arrays; 2-D ones become lists of lists), spooled to one temporary file per key; leaving the ``with`` block
    normally writes ``path`` atomically (the header's keys, then each per-frame list), after an exception
    nothing."""

    def __init__(self, path: str | Path, header: dict, per_frame: tuple[str, ...]) -> None:
        self.path = path
        self.header = header
        self.per_frame = per_frame
        self._spools: dict[str, object] = {}
        self._counts = dict.fromkeys(per_frame, 0)

    def __enter__(self) -> TruthWriter:
        import tempfile

        # beside the truth file, not in the system's temporary folder (often a RAM disk: 10^6 frames spool ~200 MB)
        folder = file_path(self.path).parent
        try:
            self._spools = {key: tempfile.TemporaryFile("w+", encoding="utf-8", dir=folder) for key in self.per_frame}
        except OSError as exc:
            for spool in self._spools.values():
                spool.close()
            raise cannot_write(self.path, exc) from None
        return self

    def append(self, values: dict[str, np.ndarray]) -> None:
        for key in self.per_frame:
            items = np.asarray(values[key]).tolist()
            if not items:
                continue
            text = json.dumps(items, separators=(",", ":"), allow_nan=False)[1:-1]
            self._spools[key].write(("," if self._counts[key] else "") + text)
            self._counts[key] += len(items)

    def __exit__(self, exc_type, exc, _tb) -> None:
        import shutil

        from hostlink.files.atomic import atomic_open

        try:
            if exc_type is None:
                with atomic_open(self.path) as fh:
                    head = json.dumps(self.header, separators=(",", ":"), allow_nan=False)
                    fh.write(head[:-1])
                    for key in self.per_frame:
                        fh.write(("," if self.header else "") + json.dumps(key) + ":[")
                        spool = self._spools[key]
                        spool.seek(0)
                        shutil.copyfileobj(spool, fh)
                        fh.write("]")
                    fh.write("}\n")
        finally:
            for spool in self._spools.values():
                spool.close()
