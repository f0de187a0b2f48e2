"""Session files (docs/file-formats.md): star observations, one row per star, frames in time order; the one reader and
the one writer.

A :class:`Session` holds columns as numpy arrays (float64 on the host) plus the frame boundaries, so every consumer
(calibration, replay, attitude, emulator replay, streaming) reads the file one way. A file is CSV, or Parquet when
its name ends in ``.parquet`` (:mod:`hostlink.files.columnar`). :func:`read_session_chunks` reads a session of any
length, or several files as one session, in chunks of whole frames in bounded memory (pyarrow's streaming CSV
reader, Parquet record batches); :func:`read_session` is the same reader, its chunks joined. Both check every row
and frame and name the first bad one in a one-line :class:`UserError`. :class:`SessionWriter` writes either format
frame by frame through a partial file renamed at the end (docs/file-formats.md).
"""

from __future__ import annotations

import csv
import glob
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import AtomicFile, cannot_write, file_path
from hostlink.files.times import parse_iso_utc_many

REQUIRED_COLUMNS = ("frame", "t_utc", "star_id", "x_px", "y_px")
#: Required columns a file may leave out: without ``t_utc`` the session's time is unknown (every t_utc empty).
MAY_BE_ABSENT = ("t_utc",)
OPTIONAL_COLUMNS = ("mag", "ra_deg", "dec_deg")


@dataclass
class Session:
    """Columns of a session file. ``ra_deg``/``dec_deg`` are None when the file has no reference directions;
    ``extra`` keeps unknown columns (as strings) so a rewrite loses nothing."""

    frame: np.ndarray  # int64
    t_utc: np.ndarray  # str (object), ISO 8601 UTC as in the file
    star_id: np.ndarray  # int64, 0 = not identified
    x_px: np.ndarray
    y_px: np.ndarray
    mag: np.ndarray | None = None
    ra_deg: np.ndarray | None = None
    dec_deg: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    @property
    def frame_starts(self) -> np.ndarray:
        """Row index where each frame starts, plus a final entry = number of rows."""
        if len(self) == 0:
            return np.zeros(1, dtype=np.int64)
        change = np.flatnonzero(np.diff(self.frame) != 0) + 1
        return np.concatenate([[0], change, [len(self)]]).astype(np.int64)

    @property
    def n_frames(self) -> int:
        return int(self.frame_starts.shape[0] - 1)

    def frame_slices(self) -> Iterator[slice]:
        starts = self.frame_starts
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            yield slice(int(a), int(b))

    @property
    def time_known(self) -> bool:
        """False when the file gives no time (every ``t_utc`` empty or the column absent): only a job that needs
        no time (calibration against J2000 directions) can use it."""
        return not (len(self) and all(str(t).strip() == "" for t in self.t_utc))

    def frame_times_jd(self) -> tuple[np.ndarray, np.ndarray]:
        """UTC two-part Julian dates (jd1, jd2) of each frame (from its first row). A session without time is a
        one-line :class:`UserError`."""
        if not self.time_known:
            raise UserError("the session gives no time (t_utc empty): this needs the UTC time of every frame")
        first = self.frame_starts[:-1]
        return parse_iso_utc_many(self.t_utc[first])

    def select(self, rows: np.ndarray) -> Session:
        """A new session with only the given rows (a boolean mask or index array)."""

        def pick(a):
            return None if a is None else a[rows]

        return Session(
            frame=self.frame[rows],
            t_utc=self.t_utc[rows],
            star_id=self.star_id[rows],
            x_px=self.x_px[rows],
            y_px=self.y_px[rows],
            mag=pick(self.mag),
            ra_deg=pick(self.ra_deg),
            dec_deg=pick(self.dec_deg),
            extra={k: v[rows] for k, v in self.extra.items()},
        )


def cell_numbers(cells) -> np.ndarray:
    """(N,) float64: each cell of an optional column (text as the file gives it) as a number, NaN where empty or not
    a number."""
    out = np.full(len(cells), np.nan)
    for i, v in enumerate(cells):
        try:
            out[i] = float(v)
        except (TypeError, ValueError, OverflowError):
            pass
    return out


def session_number(session: Session, name: str) -> np.ndarray:
    """(N,) float64: the session's optional column ``name`` (kept in ``extra``) as numbers (NaN where empty or
    absent)."""
    values = session.extra.get(name) if session.extra else None
    return np.full(len(session), np.nan) if values is None else cell_numbers(values)


def session_flag(session: Session, name: str) -> np.ndarray:
    """(N,) bool: the session's optional column ``name`` (kept in ``extra``) is "1" (False where absent)."""
    values = session.extra.get(name) if session.extra else None
    if values is None:
        return np.zeros(len(session), dtype=bool)
    return np.array([str(v).strip() == "1" for v in values], dtype=bool)


def session_filled(session: Session, name: str) -> np.ndarray:
    """(N,) bool: the session's optional column ``name`` (kept in ``extra``) holds a value (neither empty nor "nan";
    False where absent)."""
    values = session.extra.get(name) if session.extra else None
    if values is None:
        return np.zeros(len(session), dtype=bool)
    return np.array([str(v).strip().lower() not in ("", "nan") for v in values], dtype=bool)


#: The text of a star's pixel uncertainties, the optional columns ``sigma_px`` and ``blend_px``: 4 significant digits
#: (docs/file-formats.md), finer than the bounds themselves are known (they rest on a measured noise and flux).
PIXEL_SIGMA_FORMAT = ".4g"


def pixel_sigma_text(values_px: np.ndarray) -> np.ndarray:
    """(N,) object: each of ``values_px`` [px] as the text of ``sigma_px`` / ``blend_px`` (:data:`PIXEL_SIGMA_FORMAT`),
    "" where not finite (no value); formatted as Python floats (``tolist``), the same text as numpy's scalars give."""
    return np.array(
        [format(v, PIXEL_SIGMA_FORMAT) if math.isfinite(v) else "" for v in np.asarray(values_px).tolist()],
        dtype=object,
    )


#: How far a centroid may lie outside the detector extent before a session and a parameter file are declared not to
#: belong together [px]: an edge star's centroid window can extrapolate a fraction of a pixel past the last pixel.
DETECTOR_MARGIN_PX = 1.0


def check_on_detector(session: Session, image_size_px: tuple[int, int], session_name: str, params_name: str) -> None:
    """Refuse (one-line UserError) a session with a centroid off the detector of a parameter file
    (``[-0.5, w - 0.5] x [-0.5, h - 0.5]``, docs/camera-model.md, plus :data:`DETECTOR_MARGIN_PX`): the file then
    describes another camera and every result would be silently wrong."""
    width, height = image_size_px
    m = DETECTOR_MARGIN_PX
    off = (session.x_px < -0.5 - m) | (session.x_px > width - 0.5 + m)
    off |= (session.y_px < -0.5 - m) | (session.y_px > height - 0.5 + m)
    if np.any(off):
        k = int(np.argmax(off))
        raise UserError(
            f"{session_name}: {int(off.sum())} centroid(s) off the {width} x {height} px detector of {params_name} "
            f"(first: frame {int(session.frame[k])}, ({session.x_px[k]:.7g}, {session.y_px[k]:.7g}) px); "
            "the parameter file does not describe this camera"
        )


#: Frames per chunk of :func:`read_session_chunks` unless told: 10^4 frames of 10-30 stars are 1-3 x 10^5 rows,
#: some tens of MB as a :class:`Session`.
DEFAULT_CHUNK_FRAMES = 10_000
#: Bytes of CSV text parsed at a time (pyarrow's block; a row must fit in one): bounds the reader's memory.
CSV_BLOCK_BYTES = 1 << 20

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


def concatenate_sessions(parts: Sequence[Session]) -> Session:
    """One session of the rows of ``parts`` in order (the same columns in each; at least one part)."""
    if not parts:
        raise ValueError("no session to concatenate")
    if len(parts) == 1:
        return parts[0]

    def cat(name: str) -> np.ndarray | None:
        values = [getattr(p, name) for p in parts]
        return None if values[0] is None else np.concatenate(values)

    return Session(
        frame=cat("frame"),
        t_utc=cat("t_utc"),
        star_id=cat("star_id"),
        x_px=cat("x_px"),
        y_px=cat("y_px"),
        mag=cat("mag"),
        ra_deg=cat("ra_deg"),
        dec_deg=cat("dec_deg"),
        extra={k: np.concatenate([p.extra[k] for p in parts]) for k in parts[0].extra},
    )


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
    return session


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
