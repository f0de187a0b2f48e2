"""Session files (INTERFACES.md): a CSV of star observations, one row per star, frames in time order.

A :class:`Session` holds columns as numpy arrays (float64 on the host) plus the frame boundaries, so every consumer
(calibration, replay, attitude, emulator replay, streaming) reads the file one way.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import AtomicFile, cannot_write
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


#: How far a centroid may lie outside the detector extent before a session and a parameter file are declared not to
#: belong together [px]: an edge star's centroid window can extrapolate a fraction of a pixel past the last pixel.
DETECTOR_MARGIN_PX = 1.0


def check_on_detector(session: Session, image_size_px: tuple[int, int], session_name: str, params_name: str) -> None:
    """Refuse (one-line UserError) a session with a centroid off the detector of a parameter file
    (``[-0.5, w - 0.5] x [-0.5, h - 0.5]``, CAMERA_MODEL.md, plus :data:`DETECTOR_MARGIN_PX`): the file then
    describes another camera and every result would be silently wrong."""
    width, height = image_size_px
    m = DETECTOR_MARGIN_PX
    off = (session.x_px < -0.5 - m) | (session.x_px > width - 0.5 + m)
    off |= (session.y_px < -0.5 - m) | (session.y_px > height - 0.5 + m)
    if np.any(off):
        k = int(np.argmax(off))
        raise UserError(
            f"{session_name}: {int(off.sum())} centroid(s) off the {width} x {height} px detector of {params_name} "
            f"(first: frame {int(session.frame[k])}, ({session.x_px[k]:.1f}, {session.y_px[k]:.1f}) px); "
            "the parameter file does not describe this camera"
        )


def read_session(path: str | Path) -> Session:
    """Read and check a session CSV. Any malformed content is a one-line :class:`UserError` with row and column."""
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    with handle:
        reader = csv.reader(handle)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise UserError(f"{path}: empty file (expected a header row)") from None
        except (csv.Error, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: not a CSV file ({exc})") from None
        missing = [c for c in REQUIRED_COLUMNS if c not in MAY_BE_ABSENT and c not in header]
        if missing:
            raise UserError(f"{path}: missing required column(s) {', '.join(missing)}")
        if ("ra_deg" in header) != ("dec_deg" in header):
            raise UserError(f"{path}: ra_deg and dec_deg must both be present or both absent")
        try:
            rows = [r for r in reader if r]
        except (csv.Error, UnicodeDecodeError) as exc:
            raise UserError(f"{path}: unreadable CSV near line {reader.line_num} ({exc})") from None
    ncol = len(header)
    for k, row in enumerate(rows):
        if len(row) != ncol:
            raise UserError(f"{path}: line {k + 2}: expected {ncol} fields, found {len(row)}")
    cols = list(zip(*rows, strict=True)) if rows else [()] * ncol
    by_name = {name: cols[k] for k, name in enumerate(header)}

    def numeric(name: str, kind: type) -> np.ndarray:
        raw = by_name[name]
        if name in ("ra_deg", "dec_deg", "mag"):
            # unidentified stars (star_id 0) and rows without a magnitude may leave these empty
            raw = tuple("nan" if s.strip() == "" else s for s in raw)
        try:
            arr = np.array(raw, dtype=np.float64) if raw else np.zeros(0)
        except ValueError:
            for k, s in enumerate(raw):
                try:
                    float(s)
                except ValueError:
                    raise UserError(f"{path}: line {k + 2}, column {name}: not a number: {s!r}") from None
            raise
        if kind is int:
            bad = ~np.isfinite(arr) | (arr != np.round(arr))
            if np.any(bad):
                k = int(np.argmax(bad))
                raise UserError(f"{path}: line {k + 2}, column {name}: not an integer: {raw[k]!r}")
            return arr.astype(np.int64)
        if name in ("x_px", "y_px") and not np.all(np.isfinite(arr)):
            k = int(np.argmax(~np.isfinite(arr)))
            raise UserError(f"{path}: line {k + 2}, column {name}: not finite: {raw[k]!r}")
        return arr

    frame = numeric("frame", int)
    if frame.size and np.any(np.diff(frame) < 0):
        k = int(np.argmax(np.diff(frame) < 0)) + 1
        raise UserError(f"{path}: line {k + 2}: frames are not in time order (frame {frame[k]} after {frame[k - 1]})")
    t_utc = np.array(by_name["t_utc"] if "t_utc" in by_name else [""] * len(frame), dtype=object)
    session = Session(
        frame=frame,
        t_utc=t_utc,
        star_id=numeric("star_id", int),
        x_px=numeric("x_px", float),
        y_px=numeric("y_px", float),
        mag=numeric("mag", float) if "mag" in by_name else None,
        ra_deg=numeric("ra_deg", float) if "ra_deg" in by_name else None,
        dec_deg=numeric("dec_deg", float) if "dec_deg" in by_name else None,
        extra={
            k: np.array(v, dtype=object)
            for k, v in by_name.items()
            if k not in REQUIRED_COLUMNS and k not in OPTIONAL_COLUMNS
        },
    )
    if session.ra_deg is not None:
        bad = (session.star_id != 0) & ~(np.isfinite(session.ra_deg) & np.isfinite(session.dec_deg))
        if np.any(bad):
            k = int(np.argmax(bad))
            raise UserError(f"{path}: line {k + 2}: identified star without a finite ra_deg/dec_deg")
    if np.any(session.star_id < 0):
        k = int(np.argmax(session.star_id < 0))
        raise UserError(f"{path}: line {k + 2}, column star_id: negative Hipparcos number")
    if len(session) and session.time_known:
        starts = session.frame_starts[:-1]
        try:
            session.frame_times_jd()
        except ValueError as exc:
            raise UserError(f"{path}: column t_utc: {exc}") from None
        # every row of a frame must carry the frame's time
        times = np.repeat(t_utc[starts], np.diff(session.frame_starts))
        if np.any(times != t_utc):
            k = int(np.argmax(times != t_utc))
            raise UserError(f"{path}: line {k + 2}: t_utc differs from the rest of frame {frame[k]}")
    return session


class SessionWriter:
    """The one session CSV writer: rows are appended in chunks (whole frames) as they come, into ``PATH.partial``,
    which :meth:`commit` renames to ``PATH`` (atomic: a reader never sees half a file). The columns are those of the
    first chunk. Until then the partial file holds every row written so far (flushed per chunk), so a process that
    is killed loses nothing it had received. Angles are written with 10 decimals of a degree (3.6e-8 deg = 0.13 mas).
    Use as a context manager: leaving the block normally commits; leaving it by an exception keeps the partial file.
    """

    def __init__(self, path: str | Path, float_format: str = "%.6f") -> None:
        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.float_format = float_format
        self.rows = 0
        self._file = AtomicFile(self.path, temporary=self.partial, newline="")
        self._handle = None
        self._writer = None
        self._header: list[str] | None = None

    def _open(self, session: Session) -> None:
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
        self._file.commit()

    def close_partial(self) -> None:
        """Close without renaming: the rows written so far stay in :attr:`partial`."""
        self._file.abandon(keep=True)

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
    """Write a session CSV atomically (one :class:`SessionWriter` chunk)."""
    with SessionWriter(path, float_format) as writer:
        writer.append(session)
