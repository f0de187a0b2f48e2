"""Reading sessions (docs/file-formats.md): from a path, a glob pattern or several files (one session in time
order), whole or in chunks of whole frames in bounded memory; the rules that join several files into one session.
One file's rows are parsed and checked by :mod:`hostlink.files.session.parse`."""

from __future__ import annotations

import csv
import glob
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session.data import Session, concatenate_sessions
from hostlink.files.session.parse import (
    _csv_header,
    _file_chunks,
    _open_session_file,
    _open_text,
    _Progress,
    _SessionFile,
)
from hostlink.files.times import parse_iso_utc_many

#: Frames per chunk of :func:`read_session_chunks` unless told: 10^4 frames of 10-30 stars are 1-3 x 10^5 rows,
#: some tens of MB as a :class:`Session`.
DEFAULT_CHUNK_FRAMES = 10_000

#: Where a session comes from: a path, a glob pattern (``"nights/*.csv"``), or several paths; several files form one
#: session, in time order.
SessionSource = str | Path | Sequence[str | Path]


def session_paths(source: SessionSource) -> list[Path]:
    """The files of ``source``: a path; a string with ``*``, ``?`` or ``[`` that names no file, as a glob pattern
    (its matches sorted by name; none is a one-line UserError); or a list of paths."""
    if isinstance(source, str | Path):
        text = str(source)
        if isinstance(source, str) and any(c in text for c in "*?[") and not Path(text).exists():
            matches = sorted(glob.glob(text))
            if not matches:
                raise UserError(f"{text}: no file matches")
            return [Path(m) for m in matches]
        return [Path(source)]
    paths = [Path(p) for p in source]
    if not paths:
        raise UserError("no session file given")
    return paths


def read_session(source: SessionSource) -> Session:
    """Read and check a whole session: one file (CSV, or Parquet by its ending), a glob pattern or several files (one
    session in time order, see :func:`read_session_chunks`, whose chunks it joins). Any malformed content is a
    one-line :class:`UserError` naming the file, the line (CSV) or row (Parquet) and the column."""
    return concatenate_sessions(list(_chunks(source, DEFAULT_CHUNK_FRAMES, keep_empty=True)))


def read_session_chunks(source: SessionSource, chunk_frames: int = DEFAULT_CHUNK_FRAMES) -> Iterator[Session]:
    """The session of ``source`` (:func:`session_paths`) as consecutive :class:`Session` s of ``chunk_frames``
    whole frames each (the last of each file may hold fewer; a frame is never split), read in bounded memory (a CSV
    :data:`CSV_BLOCK_BYTES`, a Parquet file :data:`hostlink.files.columnar.READ_BATCH_ROWS` rows at a time, plus one
    chunk). Each chunk is checked as :func:`read_session` checks a file, with the same one-line errors, raised when
    the reader reaches them. Several files form one session: they are taken in the order of their first ``t_utc``
    (given order when none gives a time), must have the same columns, must not overlap in time, and keep their
    frame numbers (a counter may restart between files, but a file's first frame must not repeat the number of the
    previous file's last); a chunk never spans two files. An empty session yields no chunk."""
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, int | np.integer) or chunk_frames < 1:
        raise UserError(f"chunk_frames: expected a whole number >= 1, got {chunk_frames!r}")
    yield from _chunks(source, int(chunk_frames), keep_empty=False)


def _chunks(source: SessionSource, chunk_frames: int, keep_empty: bool) -> Iterator[Session]:
    paths = session_paths(source)
    if len(paths) > 1:
        paths = _time_ordered(paths)
    first: _SessionFile | None = None
    previous: tuple[Path, _Progress] | None = None
    for path in paths:
        opened = _open_session_file(path)
        if first is None:
            first = opened
        elif sorted(opened.header) != sorted(first.header):
            raise UserError(
                f"{path}: columns {','.join(opened.header)} differ from those of {first.path} "
                f"({','.join(first.header)}): the files of one session need the same columns"
            )
        progress = _Progress()
        for chunk in _file_chunks(opened, chunk_frames, progress):
            if previous is not None and len(chunk):
                _check_next_file(path, chunk, progress, *previous)
                previous = None  # checked once, at the file's first frames
            if len(chunk) or keep_empty:
                yield chunk
        if progress.last_frame is not None:
            previous = (path, progress)


def _check_next_file(path: Path, chunk: Session, progress: _Progress, before: Path, ended: _Progress) -> None:
    """Several files, one session: the next file neither repeats the previous one's last frame number (the two
    frames would merge) nor starts before it ends, and both give time or neither does."""
    if int(chunk.frame[0]) == ended.last_frame:
        raise UserError(
            f"{path}: its first frame {int(chunk.frame[0])} has the number of the last frame of {before}: the "
            "frames of one session must be told apart"
        )
    if progress.time_known != ended.time_known:
        given = "gives a time (t_utc) and {} does not" if progress.time_known else "gives no time (t_utc) and {} does"
        raise UserError(f"{path}: {given.format(before)}: the files of one session give time or none does")
    if progress.time_known and progress.first_jd < ended.last_jd:
        raise UserError(f"{path}: starts before {before} ends: the files of one session must not overlap in time")


def _time_ordered(paths: list[Path]) -> list[Path]:
    """Files in the order of their first ``t_utc`` (files without rows first); when none gives a time, as given."""
    keys: list[float | None] = []
    untimed: list[Path] = []
    for path in paths:
        text = _first_time_text(path)
        if text is None:
            keys.append(None)
        elif text.strip() == "":
            keys.append(None)
            untimed.append(path)
        else:
            try:
                jd1, jd2 = parse_iso_utc_many([text])
            except ValueError as exc:
                raise UserError(f"{path}: column t_utc: {exc}") from None
            keys.append(float(jd1[0] + jd2[0]))
    timed = [p for p, k in zip(paths, keys, strict=True) if k is not None]
    if not timed:
        return paths
    if untimed:
        raise UserError(
            f"{untimed[0]}: gives no time (t_utc empty) and {timed[0]} does: the files of one session are put in "
            "time order"
        )
    order = sorted(range(len(paths)), key=lambda k: -math.inf if keys[k] is None else keys[k])
    return [paths[k] for k in order]


def _first_time_text(path: Path) -> str | None:
    """The ``t_utc`` of a file's first row ('' without the column), None when it has no row."""
    from hostlink.files.columnar import first_parquet_value, is_parquet

    if is_parquet(path):
        return first_parquet_value(path, "t_utc")
    header = _csv_header(path)
    with _open_text(path) as handle:
        reader = csv.reader(handle)
        try:
            next(reader)
            row = next((r for r in reader if r), None)
        except (csv.Error, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: unreadable CSV near line {reader.line_num} ({exc})") from None
    if row is None:
        return None
    k = header.index("t_utc") if "t_utc" in header else None
    return row[k] if k is not None and k < len(row) else ""
