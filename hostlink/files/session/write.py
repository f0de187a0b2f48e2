"""Writing sessions (docs/file-formats.md): the one writer, CSV or Parquet, frame by frame through a partial file
renamed at the end."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import AtomicFile, cannot_write, file_path
from hostlink.files.session.data import REQUIRED_COLUMNS, Session


class SessionWriter:
    """The one session writer: rows are appended in chunks (whole frames) as they come, into a partial file next to
    ``PATH`` (``.NAME.<random>.partial``, created exclusively: :class:`hostlink.files.atomic.AtomicFile`; its path is
    :attr:`partial` once the first chunk is written), which :meth:`commit` renames to ``PATH`` (atomic: a reader
    never sees half a file). The columns are those of the first chunk. Use as a context manager: leaving the block
    normally commits; leaving it by an exception keeps the partial file.

    CSV (any ending but ``.parquet``): the partial file holds every row written so far (flushed per chunk), so a
    process that is killed loses nothing it had received. Angles are written with 10 decimals of a degree
    (3.6e-8 deg = 0.13 mas), centroids with ``float_format``.

    Parquet (``PATH.parquet``, :mod:`hostlink.files.columnar`): values are stored exactly (float64;
    ``float_format`` does not apply), in row groups of whole frames written every
    :data:`~hostlink.files.columnar.ROW_GROUP_ROWS` rows. A Parquet file is readable only once its footer is
    written: :meth:`commit` and :meth:`close_partial` write it, so after an exception (a dropped link, Ctrl-C) the
    partial file is a readable session; a process killed outright leaves an unreadable one.
    """

    def __init__(self, path: str | Path, float_format: str = "%.6f") -> None:
        from hostlink.files.columnar import is_parquet

        self.path = file_path(path)
        self.float_format = float_format
        self.rows = 0
        self.columnar = is_parquet(self.path)
        self._file = AtomicFile(self.path, suffix=".partial", newline="", binary=self.columnar)
        self._handle = None
        self._writer = None
        self._sink = None
        self._header: list[str] | None = None

    @property
    def partial(self) -> Path | None:
        """The partial file (None before the first chunk)."""
        return self._file.temporary

    def _open(self, session: Session) -> None:
        if self.columnar:
            from hostlink.files.columnar import ParquetSink

            self._handle = self._file.open()
            try:
                self._sink = ParquetSink(self._handle, session)
            except OSError as exc:
                raise cannot_write(self.path, exc) from None
            self._header = self._sink.names
            return
        header = list(REQUIRED_COLUMNS)
        if session.mag is not None:
            header.append("mag")
        if session.ra_deg is not None and session.dec_deg is not None:
            header += ["ra_deg", "dec_deg"]
        header += list(session.extra)
        self._handle = self._file.open()
        self._writer = csv.writer(self._handle, lineterminator="\n")
        self._header = header
        self._write([header])

    def _write(self, rows) -> None:
        try:
            self._writer.writerows(rows)
            self._handle.flush()
        except OSError as exc:
            raise cannot_write(self.path, exc) from None

    def append(self, session: Session) -> None:
        """Append the rows of ``session`` (whole frames, in time order, with the columns of the first chunk)."""
        if self._header is None:
            self._open(session)
        if self._sink is not None:
            try:
                self._sink.append(session)
            except OSError as exc:
                raise cannot_write(self.path, exc) from None
            self.rows += len(session)
            return
        ff = self.float_format
        cols: list[list[str]] = [
            [str(int(v)) for v in session.frame],
            [str(v) for v in session.t_utc],
            [str(int(v)) for v in session.star_id],
            [ff % v for v in session.x_px],
            [ff % v for v in session.y_px],
        ]
        if "mag" in self._header:
            cols.append(["%.3f" % v if np.isfinite(v) else "" for v in _column(session.mag, len(session))])
        if "ra_deg" in self._header:
            cols.append(["%.10f" % v if np.isfinite(v) else "" for v in _column(session.ra_deg, len(session))])
            cols.append(["%.10f" % v if np.isfinite(v) else "" for v in _column(session.dec_deg, len(session))])
        for name in self._header[len(cols) :]:
            values = session.extra.get(name)
            cols.append([""] * len(session) if values is None else [str(v) for v in values])
        self._write(zip(*cols, strict=True))
        self.rows += len(session)

    def commit(self) -> None:
        """Rename the partial file to ``path`` (fsync-ed: :class:`hostlink.files.atomic.AtomicFile`; an empty
        session is written as its header)."""
        if self._header is None:
            self._open(Session(*(np.zeros(0, dtype=t) for t in (np.int64, object, np.int64, float, float))))
        self._close_sink()
        self._file.commit()

    def close_partial(self) -> None:
        """Close without renaming: the rows written so far stay in :attr:`partial` (a Parquet file with its
        footer, so readable)."""
        try:
            self._close_sink()
        finally:
            self._file.abandon(keep=True)

    def discard(self) -> None:
        """Close and remove the partial file: nothing of this writer stays (a simulation that failed part way)."""
        try:
            self._close_sink()
        except UserError:
            pass  # the write is abandoned anyway; the error that got us here is the one to report
        finally:
            self._file.abandon(keep=False)

    def _close_sink(self) -> None:
        if self._sink is not None:
            sink, self._sink = self._sink, None
            try:
                sink.close()
            except OSError as exc:
                raise cannot_write(self.path, exc) from None

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, _tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.close_partial()


def _column(values: np.ndarray | None, n: int) -> np.ndarray:
    return np.full(n, np.nan) if values is None else values


def write_session(path: str | Path, session: Session, float_format: str = "%.6f") -> None:
    """Write a session atomically (one :class:`SessionWriter` chunk): CSV, or Parquet for ``PATH.parquet``."""
    with SessionWriter(path, float_format) as writer:
        writer.append(session)
