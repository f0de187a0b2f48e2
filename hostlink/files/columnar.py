"""The columnar session format (docs/file-formats.md, "Session file, Parquet"): the schema, and the Parquet side of
the one session reader and writer (:mod:`hostlink.files.session`), through pyarrow.

A session is the same table as the CSV: one row per star observation, frames in time order. Columns:
``frame`` int64, ``t_utc`` string (the ISO 8601 UTC text, exactly as in a CSV: a leap second ``23:59:60`` has no
Arrow timestamp), ``star_id`` int64, ``x_px``/``y_px`` float64 [px], optional ``mag`` float64 and ``ra_deg``/
``dec_deg`` float64 [deg] (null = none, as an empty CSV cell), and extra columns as strings. Every row group holds
whole frames, so a reader can take a row group at a time without splitting a frame. The key ``hostlink.session`` of
the file's metadata holds :data:`SCHEMA_VERSION`.

pyarrow is imported when a Parquet file is read or written, not when this module is imported.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hostlink.errors import UserError

if TYPE_CHECKING:
    import pyarrow as pa

    from hostlink.files.session import Session

#: File name endings read and written as Parquet (any other: CSV).
PARQUET_SUFFIXES = (".parquet",)
#: Version of the layout below, in the file's key-value metadata under ``hostlink.session``.
SCHEMA_VERSION = "1"
#: Rows per row group the writer aims at (it cuts between frames, at or after this many rows): large enough for
#: column compression and fast scans, small enough that a reader holds one at a time in a few MB.
ROW_GROUP_ROWS = 131_072
#: Rows per record batch the reader takes at a time (bounds its memory; frames may straddle two batches, the
#: session reader rejoins them).
READ_BATCH_ROWS = 32_768
#: Bytes the Parquet reader buffers per column (bounds its memory whatever the row group size).
READ_BUFFER_BYTES = 1 << 20
#: Parquet compression of the writer: dictionary encoding already packs the repeated t_utc of a frame, and snappy
#: keeps reading near disk speed for a few more bytes than zstd (sizes and read times in docs/file-formats.md).
COMPRESSION = "snappy"


def is_parquet(path: str | Path) -> bool:
    """True when ``path`` names a Parquet session (by its ending, :data:`PARQUET_SUFFIXES`, any case)."""
    return Path(path).suffix.lower() in PARQUET_SUFFIXES


def session_schema(has_mag: bool, has_radec: bool, extra: list[str]) -> pa.Schema:
    """The Parquet schema of a session with the given optional columns (module docstring)."""
    import pyarrow as pa

    fields = [
        pa.field("frame", pa.int64(), nullable=False),
        pa.field("t_utc", pa.string(), nullable=False),
        pa.field("star_id", pa.int64(), nullable=False),
        pa.field("x_px", pa.float64(), nullable=False),
        pa.field("y_px", pa.float64(), nullable=False),
    ]
    if has_mag:
        fields.append(pa.field("mag", pa.float64()))
    if has_radec:
        fields += [pa.field("ra_deg", pa.float64()), pa.field("dec_deg", pa.float64())]
    fields += [pa.field(name, pa.string()) for name in extra]
    return pa.schema(fields, metadata={"hostlink.session": SCHEMA_VERSION})


def session_table(session: Session, schema: pa.Schema) -> pa.Table:
    """The rows of ``session`` as a table of ``schema`` (:func:`session_schema`): NaN magnitudes and directions
    become nulls, extra columns the session lacks are nulls."""
    import pyarrow as pa

    n = len(session)

    def floats(values: np.ndarray | None) -> pa.Array:
        v = np.full(n, np.nan) if values is None else np.asarray(values, dtype=np.float64)
        return pa.array(v, type=pa.float64(), mask=~np.isfinite(v))

    columns: list[pa.Array] = []
    for name in schema.names:
        if name in ("frame", "star_id"):
            columns.append(pa.array(np.asarray(getattr(session, name), dtype=np.int64), type=pa.int64()))
        elif name == "t_utc":
            columns.append(pa.array([str(t) for t in session.t_utc], type=pa.string()))
        elif name in ("x_px", "y_px"):
            columns.append(pa.array(np.asarray(getattr(session, name), dtype=np.float64), type=pa.float64()))
        elif name in ("mag", "ra_deg", "dec_deg"):
            columns.append(floats(getattr(session, name)))
        else:
            values = session.extra.get(name)
            cells = [None] * n if values is None else [str(v) for v in values]
            columns.append(pa.array(cells, type=pa.string()))
    return pa.Table.from_arrays(columns, schema=schema)


class ParquetSink:
    """Row groups of whole frames into an open binary handle: :meth:`append` buffers sessions and writes a row group
    once :data:`ROW_GROUP_ROWS` rows are waiting; :meth:`close` writes the rest and the file's footer (the handle
    stays open: the atomic writer fsyncs and renames it)."""

    def __init__(self, handle, session: Session) -> None:
        import pyarrow.parquet as pq

        from hostlink.files.session import OPTIONAL_COLUMNS, REQUIRED_COLUMNS

        self.schema = session_schema(
            session.mag is not None,
            session.ra_deg is not None and session.dec_deg is not None,
            [k for k in session.extra if k not in REQUIRED_COLUMNS and k not in OPTIONAL_COLUMNS],
        )
        self._writer = pq.ParquetWriter(handle, self.schema, compression=COMPRESSION)
        self._waiting: list[pa.Table] = []
        self._rows = 0

    @property
    def names(self) -> list[str]:
        return list(self.schema.names)

    def append(self, session: Session) -> None:
        if len(session):
            self._waiting.append(session_table(session, self.schema))
            self._rows += len(session)
        if self._rows >= ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        import pyarrow as pa

        if self._waiting:
            table = pa.concat_tables(self._waiting)
            self._writer.write_table(table, row_group_size=max(1, table.num_rows))
        self._waiting, self._rows = [], 0

    def close(self) -> None:
        self._flush()
        self._writer.close()


def open_parquet(path: Path) -> tuple[list[str], Iterator[dict[str, pa.Array]]]:
    """(column names, batches) of a Parquet session: each batch maps a column name to an Arrow array of up to
    :data:`READ_BATCH_ROWS` rows, read one at a time. A missing or unreadable file is a one-line UserError."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        # read column chunks as they are decoded, through a 1 MB buffer: without it pyarrow loads a whole row group
        handle = pq.ParquetFile(path, pre_buffer=False, buffer_size=READ_BUFFER_BYTES)
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (pa.ArrowException, ValueError) as exc:
        raise UserError(f"{path}: not a Parquet file ({_first_line(exc)})") from None
    names = list(handle.schema_arrow.names)

    def batches() -> Iterator[dict[str, pa.Array]]:
        try:
            for batch in handle.iter_batches(batch_size=READ_BATCH_ROWS):
                yield {name: batch.column(k) for k, name in enumerate(batch.schema.names)}
        except (pa.ArrowException, OSError) as exc:
            raise UserError(f"{path}: unreadable Parquet data ({_first_line(exc)})") from None
        finally:
            handle.close()

    return names, batches()


def first_parquet_value(path: Path, column: str) -> str | None:
    """The first value of a column of a Parquet session as text ('' when the file lacks the column or the value is
    null; None when the file has no row), without reading the rest: how several files are put in time order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        handle = pq.ParquetFile(path)
        try:
            if handle.metadata.num_rows == 0:
                return None
            if column not in handle.schema_arrow.names:
                return ""
            batch = next(handle.iter_batches(batch_size=1, columns=[column]))
            value = batch.column(0)[0].as_py()
        finally:
            handle.close()
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (pa.ArrowException, OSError, ValueError, StopIteration) as exc:
        raise UserError(f"{path}: not a readable Parquet file ({_first_line(exc)})") from None
    return "" if value is None else str(value)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
