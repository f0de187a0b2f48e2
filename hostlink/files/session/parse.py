"""One session file's rows (CSV through pyarrow's streaming reader, or Parquet batches) into checked
:class:`~hostlink.files.session.data.Session` chunks of whole frames: the header, every cell's number or text, and
the checks a row or a frame needs, each failure a one-line :class:`UserError` naming the file, line or row and
column (docs/file-formats.md)."""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session.data import (
    IMAGE_SIZE_COLUMNS,
    MAY_BE_ABSENT,
    OPTIONAL_COLUMNS,
    REQUIRED_COLUMNS,
    Session,
    concatenate_sessions,
)

#: Bytes of CSV text parsed at a time (pyarrow's block; a row must fit in one): bounds the reader's memory.
CSV_BLOCK_BYTES = 1 << 20


@dataclass
class _SessionFile:
    """One open session file: its column names, its rows as batches of Arrow arrays, and how a row is named in an
    error (``line N`` of a CSV, counting the header; ``row N`` of a Parquet file, from 1)."""

    path: Path
    header: list[str]
    batches: Iterator[dict]
    where: Callable[[int], str]


@dataclass
class _Progress:
    """What the reader knows of the file it reads (and, at the end, of the last file): its last frame number,
    whether it gives time, and the UTC of its first and last frame (jd1 + jd2)."""

    last_frame: int | None = None
    time_known: bool | None = None
    first_jd: float | None = None
    last_jd: float | None = None


def _open_session_file(path: Path) -> _SessionFile:
    from hostlink.files.columnar import is_parquet, open_parquet

    if is_parquet(path):
        header, batches = open_parquet(path)
        _check_header(path, header)
        return _SessionFile(path, header, batches, lambda k: f"row {k + 1}")
    header = _csv_header(path)
    _check_header(path, header)
    return _SessionFile(path, header, _csv_batches(path, header), lambda k: f"line {k + 2}")


def _open_text(path: Path):
    try:
        return path.open(newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None


def _csv_header(path: Path) -> list[str]:
    with _open_text(path) as handle:
        try:
            return [h.strip() for h in next(csv.reader(handle))]
        except StopIteration:
            raise UserError(f"{path}: empty file (expected a header row)") from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: not a CSV file ({exc})") from None


def _json_kind(path: Path) -> str | None:
    """What a JSON file given as a session is, in a few words (a simulation truth file, a camera parameter file, a
    JSON file), from its first 64 kB; None when it is not JSON text."""
    try:
        with path.open(encoding="utf-8-sig", errors="replace") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    if not head.lstrip().startswith(("{", "[")):
        return None
    if '"startracker-companion simulation truth"' in head:
        return "a simulation truth file (the session it describes is the CSV beside it, without .truth.json)"
    if '"focal_length_mm"' in head and '"image_size_px"' in head:
        return "a camera parameter file (give it to --nominal or --params)"
    return "a JSON file"


def _check_header(path: Path, header: list[str]) -> None:
    missing = [c for c in REQUIRED_COLUMNS if c not in MAY_BE_ABSENT and c not in header]
    if missing:
        what = _json_kind(path) if header and header[0].lstrip().startswith(("{", "[")) else None
        if what:
            raise UserError(f"{path}: {what}, not a session (a CSV or Parquet table of star observations)")
        raise UserError(f"{path}: missing required column(s) {', '.join(missing)}")
    if ("ra_deg" in header) != ("dec_deg" in header):
        raise UserError(f"{path}: ra_deg and dec_deg must both be present or both absent")
    if (IMAGE_SIZE_COLUMNS[0] in header) != (IMAGE_SIZE_COLUMNS[1] in header):
        raise UserError(f"{path}: {' and '.join(IMAGE_SIZE_COLUMNS)} must both be present or both absent")
    twice = sorted({h for h in header if header.count(h) > 1})
    if twice:
        raise UserError(f"{path}: column {twice[0]} appears more than once")


def _csv_batches(path: Path, header: list[str]) -> Iterator[dict]:
    """The rows of a CSV after its header, :data:`CSV_BLOCK_BYTES` at a time, every column as Arrow text (pyarrow's
    streaming reader; quoting as Python's csv module, blank lines skipped)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    read = pacsv.ReadOptions(skip_rows=1, column_names=header, block_size=CSV_BLOCK_BYTES, use_threads=False)
    convert = pacsv.ConvertOptions(
        column_types=dict.fromkeys(header, pa.string()), strings_can_be_null=False, quoted_strings_can_be_null=False
    )
    try:
        reader = pacsv.open_csv(path, read_options=read, convert_options=convert)
        for batch in reader:
            yield {name: batch.column(k) for k, name in enumerate(header)}
    except pa.ArrowInvalid as exc:
        raise _csv_failure(path, header, exc) from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _csv_failure(path: Path, header: list[str], exc: Exception) -> UserError:
    """The one-line error for a CSV that pyarrow refused: the first line with the wrong number of fields, found by
    reading the file again with Python's csv module (the error path only), else pyarrow's reason."""
    ncol = len(header)
    with _open_text(path) as handle:
        reader = csv.reader(handle)
        try:
            next(reader)
            k = 0
            for row in reader:
                if not row:
                    continue
                if len(row) != ncol:
                    return UserError(f"{path}: line {k + 2}: expected {ncol} fields, found {len(row)}")
                k += 1
        except (csv.Error, UnicodeDecodeError) as err:
            return UserError(f"{path}: unreadable CSV near line {reader.line_num} ({err})")
    reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return UserError(f"{path}: unreadable CSV ({reason})")


def _file_chunks(source: _SessionFile, chunk_frames: int, progress: _Progress) -> Iterator[Session]:
    """Checked chunks of ``chunk_frames`` whole frames of one file: batches are converted as they come, held until
    enough frames are complete (the last frame of a batch may go on in the next), then cut at frame boundaries."""
    pending: list[Session] = []
    pending_row0 = 0  # file row of pending[0]'s first row
    pending_frames = 0
    rows = 0
    for columns in source.batches:
        part = _part(source, columns, rows)
        rows += len(part)
        if not len(part):
            continue
        runs = 1 + int(np.count_nonzero(np.diff(part.frame)))
        if pending and part.frame[0] == pending[-1].frame[-1]:
            runs -= 1
        pending.append(part)
        pending_frames += runs
        if pending_frames - 1 >= chunk_frames:  # the last frame may go on in the next batch
            buffer = concatenate_sessions(pending)
            starts = buffer.frame_starts
            ready = (len(starts) - 2) // chunk_frames * chunk_frames
            for a in range(0, ready, chunk_frames):
                lo, hi = int(starts[a]), int(starts[a + chunk_frames])
                yield _checked(source, buffer.select(slice(lo, hi)), pending_row0 + lo, progress)
            cut = int(starts[ready])
            pending = [buffer.select(slice(cut, None))]
            pending_row0 += cut
            pending_frames -= ready
    if not pending:
        if rows == 0:
            yield _empty_session(source.header)
        return
    buffer = concatenate_sessions(pending)
    starts = buffer.frame_starts
    n_frames = len(starts) - 1
    for a in range(0, n_frames, chunk_frames):
        lo, hi = int(starts[a]), int(starts[min(a + chunk_frames, n_frames)])
        yield _checked(source, buffer.select(slice(lo, hi)), pending_row0 + lo, progress)


def _empty_session(header: list[str]) -> Session:
    def none(dtype) -> np.ndarray:
        return np.zeros(0, dtype=dtype)

    return Session(
        frame=none(np.int64),
        t_utc=none(object),
        star_id=none(np.int64),
        x_px=none(np.float64),
        y_px=none(np.float64),
        mag=none(np.float64) if "mag" in header else None,
        ra_deg=none(np.float64) if "ra_deg" in header else None,
        dec_deg=none(np.float64) if "dec_deg" in header else None,
        extra={k: none(object) for k in header if k not in REQUIRED_COLUMNS and k not in OPTIONAL_COLUMNS},
    )


def _part(source: _SessionFile, columns: dict, row0: int) -> Session:
    """One batch of rows -> a Session, with the checks that need one row at a time (numbers, integers, finite
    centroids, identified stars' directions, star_id >= 0). ``row0``: the file row of the batch's first row."""
    path, where = source.path, source.where

    def number(name: str, **how) -> np.ndarray:
        return _numbers(path, where, row0, name, columns[name], **how)

    def optional(name: str) -> np.ndarray | None:
        return number(name, may_be_empty=True) if name in columns else None

    n = len(columns[source.header[0]])
    session = Session(
        frame=number("frame", integer=True),
        t_utc=_texts(path, "t_utc", columns["t_utc"]) if "t_utc" in columns else np.full(n, "", dtype=object),
        star_id=number("star_id", integer=True),
        x_px=number("x_px", finite=True),
        y_px=number("y_px", finite=True),
        mag=optional("mag"),
        ra_deg=optional("ra_deg"),
        dec_deg=optional("dec_deg"),
        extra={k: _texts(path, k, columns[k]) for k in source.header if k not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS},
    )
    if session.ra_deg is not None:
        bad = (session.star_id != 0) & ~(np.isfinite(session.ra_deg) & np.isfinite(session.dec_deg))
        if np.any(bad):
            k = int(np.argmax(bad))
            raise UserError(f"{path}: {where(row0 + k)}: identified star without a finite ra_deg/dec_deg")
    if np.any(session.star_id < 0):
        k = int(np.argmax(session.star_id < 0))
        raise UserError(f"{path}: {where(row0 + k)}, column star_id: negative Hipparcos number")
    if IMAGE_SIZE_COLUMNS[0] in columns:
        _check_image_sizes(source, columns, row0)
    return session


def _check_image_sizes(source: _SessionFile, columns: dict, row0: int) -> None:
    """The image width and height of each row: both empty (not known) or both a whole number of pixels in
    1..MAX_IMAGE_SIDE_PX (the sides a parameter file's ``image_size_px`` may have)."""
    from onboard.params import MAX_IMAGE_SIDE_PX

    path, where = source.path, source.where
    sides = [_numbers(path, where, row0, name, columns[name], may_be_empty=True) for name in IMAGE_SIZE_COLUMNS]
    for name, side in zip(IMAGE_SIZE_COLUMNS, sides, strict=True):
        given = np.isfinite(side)
        bad = given & ((side != np.round(side)) | (side < 1) | (side > MAX_IMAGE_SIDE_PX))
        if np.any(bad):
            k = int(np.argmax(bad))
            raise UserError(
                f"{path}: {where(row0 + k)}, column {name}: expected a whole number of pixels in "
                f"1..{MAX_IMAGE_SIDE_PX}, got {columns[name][k].as_py()!r}"
            )
    half = np.isfinite(sides[0]) != np.isfinite(sides[1])
    if np.any(half):
        k = int(np.argmax(half))
        raise UserError(
            f"{path}: {where(row0 + k)}: {' and '.join(IMAGE_SIZE_COLUMNS)} must both be given or both empty"
        )


def _checked(source: _SessionFile, chunk: Session, row0: int, progress: _Progress) -> Session:
    """The checks that need whole frames: frame numbers never decreasing (also from the previous chunk), every row
    of a frame at the frame's time, valid UTC times, and time given in every frame of a file or in none."""
    path, where, frame, t_utc = source.path, source.where, chunk.frame, chunk.t_utc
    before = np.concatenate([[frame[0] if progress.last_frame is None else progress.last_frame], frame[:-1]])
    if np.any(frame < before):
        k = int(np.argmax(frame < before))
        raise UserError(f"{path}: {where(row0 + k)}: frames are not in time order (frame {frame[k]} after {before[k]})")
    known = chunk.time_known
    if progress.time_known is None:
        progress.time_known = known
    elif known != progress.time_known:
        k = int(np.argmax([str(t).strip() != "" for t in t_utc])) if known else 0
        state = "given" if known else "empty"
        raise UserError(
            f"{path}: {where(row0 + k)}: t_utc {state} here but not in the frames before (a session gives the time "
            "of every frame or of none)"
        )
    if known:
        try:
            jd1, jd2 = chunk.frame_times_jd()
        except ValueError as exc:
            raise UserError(f"{path}: column t_utc: {exc}") from None
        starts = chunk.frame_starts
        times = np.repeat(t_utc[starts[:-1]], np.diff(starts))
        if np.any(times != t_utc):
            k = int(np.argmax(times != t_utc))
            raise UserError(f"{path}: {where(row0 + k)}: t_utc differs from the rest of frame {frame[k]}")
        if progress.first_jd is None:
            progress.first_jd = float(jd1[0] + jd2[0])
        progress.last_jd = float(jd1[-1] + jd2[-1])
    progress.last_frame = int(frame[-1])
    return chunk


def _texts(path: Path, name: str, values) -> np.ndarray:
    """An Arrow column -> object array of str (null -> ''); ``t_utc`` must be text, extra columns are turned into
    text."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if not (pa.types.is_string(values.type) or pa.types.is_large_string(values.type)):
        if name == "t_utc":
            raise UserError(f"{path}: column t_utc: expected ISO 8601 UTC text, found {values.type}")
        values = pc.cast(values, pa.string())
    if values.null_count:
        values = values.fill_null("")
    if name == "t_utc":
        # one str object per distinct time (a frame's rows share it), not one per row: a tenth of the memory
        encoded = values.dictionary_encode()
        return encoded.dictionary.to_numpy(zero_copy_only=False)[encoded.indices.to_numpy(zero_copy_only=False)]
    return values.to_numpy(zero_copy_only=False)


def _numbers(
    path: Path,
    where: Callable[[int], str],
    row0: int,
    name: str,
    values,
    *,
    integer: bool = False,
    finite: bool = False,
    may_be_empty: bool = False,
) -> np.ndarray:
    """An Arrow column (text or numbers) -> float64, or int64 when ``integer`` (whole values only); ``may_be_empty``:
    an empty cell or null is NaN (magnitudes and directions of unidentified stars); ``finite``: NaN and infinity are
    refused. Text is parsed by Arrow, and by Python's ``float`` where Arrow refuses (which then names the bad cell)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    kind = values.type
    text = pa.types.is_string(kind) or pa.types.is_large_string(kind)
    if not (text or pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_null(kind)):
        raise UserError(f"{path}: column {name}: expected numbers, found {kind}")
    if values.null_count and not may_be_empty and not text:
        k = int(np.argmax(values.is_null().to_numpy(zero_copy_only=False)))
        raise UserError(f"{path}: {where(row0 + k)}, column {name}: empty")
    arr = None
    if text and not (values.null_count and not may_be_empty):
        cells = values
        if may_be_empty:
            cells = pc.if_else(pc.equal(pc.utf8_trim_whitespace(cells), ""), pa.scalar(None, kind), cells)
        try:
            arr = pc.cast(cells, pa.float64()).to_numpy(zero_copy_only=False)
        except pa.ArrowInvalid:
            arr = None  # Python's float decides, and names the cell
    if arr is None and text:
        arr = _python_numbers(path, where, row0, name, values.to_pylist(), may_be_empty)
    elif arr is None:
        arr = pc.cast(values, pa.float64()).to_numpy(zero_copy_only=False)
    if integer:
        # from 2^53 on, float64 no longer holds every integer (2^53 + 1 reads as 2^53; int64 ends at 2^63): refused,
        # not rounded
        bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (np.abs(arr) >= 2.0**53)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise UserError(f"{path}: {where(row0 + k)}, column {name}: not an integer: {values[k].as_py()!r}")
        return arr.astype(np.int64)
    if finite and not np.all(np.isfinite(arr)):
        k = int(np.argmax(~np.isfinite(arr)))
        raise UserError(f"{path}: {where(row0 + k)}, column {name}: not finite: {values[k].as_py()!r}")
    return arr


def _python_numbers(
    path: Path, where: Callable[[int], str], row0: int, name: str, cells: list, may_be_empty: bool
) -> np.ndarray:
    raw = ["" if c is None else c for c in cells]
    if may_be_empty:
        raw = ["nan" if s.strip() == "" else s for s in raw]
    try:
        return np.array(raw, dtype=np.float64) if raw else np.zeros(0)
    except ValueError:
        for k, s in enumerate(raw):
            try:
                float(s)
            except ValueError:
                raise UserError(f"{path}: {where(row0 + k)}, column {name}: not a number: {s!r}") from None
        raise
