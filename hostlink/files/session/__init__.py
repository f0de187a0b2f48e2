"""Session files (docs/file-formats.md): star observations, one row per star, frames in time order; the one reader and
the one writer.

A :class:`Session` holds columns as numpy arrays (float64 on the host) plus the frame boundaries, so every consumer
(calibration, replay, attitude, emulator replay, streaming) reads the file one way. A file is CSV, or Parquet when
its name ends in ``.parquet`` (:mod:`hostlink.files.columnar`). :func:`read_session_chunks` reads a session of any
length, or several files as one session, in chunks of whole frames in bounded memory (pyarrow's streaming CSV
reader, Parquet record batches); :func:`read_session` is the same reader, its chunks joined. Both check every row
and frame and name the first bad one in a one-line :class:`UserError`. :class:`SessionWriter` writes either format
frame by frame through a partial file renamed at the end (docs/file-formats.md).

Its modules, one job each (every name is imported from here): :mod:`~hostlink.files.session.data` (the
:class:`Session` and its selection, the size of its images and the check against a camera's detector),
:mod:`~hostlink.files.session.columns` (the optional columns), :mod:`~hostlink.files.session.read` (sources,
chunks, several files as one session), :mod:`~hostlink.files.session.parse` (one file's rows, CSV or Parquet, parsed
and checked) and :mod:`~hostlink.files.session.write` (the writer).
"""

from __future__ import annotations

from hostlink.files.session.columns import (
    PIXEL_SIGMA_FORMAT,
    cell_numbers,
    pixel_sigma_text,
    session_filled,
    session_flag,
    session_number,
)
from hostlink.files.session.data import (
    DETECTOR_MARGIN_PX,
    IMAGE_SIZE_COLUMNS,
    MAY_BE_ABSENT,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    Session,
    check_on_detector,
    concatenate_sessions,
    image_size_mismatch,
    image_sizes_px,
)
from hostlink.files.session.parse import CSV_BLOCK_BYTES  # read there: a caller changes it in session.parse
from hostlink.files.session.read import (
    DEFAULT_CHUNK_FRAMES,
    SessionSource,
    read_session,
    read_session_chunks,
    session_paths,
)
from hostlink.files.session.write import SessionWriter, write_session

__all__ = [
    "CSV_BLOCK_BYTES",
    "DEFAULT_CHUNK_FRAMES",
    "DETECTOR_MARGIN_PX",
    "IMAGE_SIZE_COLUMNS",
    "MAY_BE_ABSENT",
    "OPTIONAL_COLUMNS",
    "PIXEL_SIGMA_FORMAT",
    "REQUIRED_COLUMNS",
    "Session",
    "SessionSource",
    "SessionWriter",
    "cell_numbers",
    "check_on_detector",
    "concatenate_sessions",
    "image_size_mismatch",
    "image_sizes_px",
    "pixel_sigma_text",
    "read_session",
    "read_session_chunks",
    "session_filled",
    "session_flag",
    "session_number",
    "session_paths",
    "write_session",
]
