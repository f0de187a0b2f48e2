"""The session in memory (docs/file-formats.md): the :class:`Session` columns and their frames, selecting and joining
rows, the size of the images its centroids were measured in, and the check that a session belongs to a camera's
detector."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from hostlink.errors import UserError
from hostlink.files.times import parse_iso_utc_many

REQUIRED_COLUMNS = ("frame", "t_utc", "star_id", "x_px", "y_px")
#: Required columns a file may leave out: without ``t_utc`` the session's time is unknown (every t_utc empty).
MAY_BE_ABSENT = ("t_utc",)
OPTIONAL_COLUMNS = ("mag", "ra_deg", "dec_deg")
#: Optional columns, both or neither (kept as text in :attr:`Session.extra`): the width and height [px] of the image a
#: row's centroid was measured in (``hostlink centroid`` writes them; empty = not known), checked against a parameter
#: file's ``image_size_px`` by :func:`check_on_detector`.
IMAGE_SIZE_COLUMNS = ("image_width_px", "image_height_px")


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


#: How far a centroid may lie outside the detector extent before a session and a parameter file are declared not to
#: belong together [px]: an edge star's centroid window can extrapolate a fraction of a pixel past the last pixel.
DETECTOR_MARGIN_PX = 1.0


#: Largest binning factor the size check names (:func:`image_size_mismatch`): cameras bin 2 x 2 to 4 x 4, a few 8 x 8.
MAX_BINNING = 16


def image_sizes_px(session: Session) -> np.ndarray | None:
    """(N, 2) int64: each row's image width and height [px] from :data:`IMAGE_SIZE_COLUMNS` (0 where a cell is empty
    or not a whole number); None unless the session has both columns (the reader refuses one without the other)."""
    if not all(name in session.extra for name in IMAGE_SIZE_COLUMNS):
        return None
    return np.stack([_whole_cells(session.extra[name]) for name in IMAGE_SIZE_COLUMNS], axis=1)


def _whole_cells(cells: np.ndarray) -> np.ndarray:
    """(N,) int64 of text cells: the whole number each holds, 0 where empty or not a whole number >= 1 (parsed by
    pyarrow in one pass: a session may hold 10^7 rows)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    text = pc.utf8_trim_whitespace(pa.array(np.asarray(cells, dtype=object).tolist(), type=pa.string()))
    text = pc.if_else(pc.equal(text, ""), pa.scalar(None, pa.string()), text)
    try:
        values = pc.cast(text, pa.float64()).to_numpy(zero_copy_only=False)
    except pa.ArrowInvalid:  # a cell that is not a number: each cell on its own (never from the reader, which checks)
        values = np.array([_number(c) for c in text.to_pylist()], dtype=np.float64)
    whole = np.isfinite(values) & (values >= 1) & (values == np.round(values)) & (values < 2.0**53)
    return np.where(whole, values, 0).astype(np.int64)


def _number(cell: str | None) -> float:
    try:
        return float(cell)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def image_size_mismatch(images_px: tuple[int, int], detector_px: tuple[int, int]) -> str:
    """What images of ``images_px`` (width, height) [px] measured against a detector of ``detector_px`` look like, as
    the end of a one-line error: the detector turned 90 deg (width and height swapped), binned k x k (each side the
    detector's // k: the nominal of the binned camera has image_size_px the binned size, pixel_pitch_um x k and the
    principal point (x0 - (k - 1) / 2) / k, as scripts/newcamera.py writes it), a window of it (smaller on both sides:
    the principal point less the window's origin), or another camera."""
    (w, h), (width, height) = images_px, detector_px
    if (w, h) == (height, width):
        return (
            "; turned 90 deg? give a nominal for the turned images (image_size_px "
            f"[{w}, {h}], the principal point turned with them) or turn the images back"
        )
    k = round(width / w) if w else 0
    if 2 <= k <= MAX_BINNING and (width // k, height // k) == (w, h):
        return (
            f"; binned {k} x {k}? give a nominal for the binned pixels (image_size_px [{w}, {h}], "
            f"pixel_pitch_um x {k}, principal point (x0 - {(k - 1) / 2:g}) / {k}, (y0 - {(k - 1) / 2:g}) / {k})"
        )
    if w <= width and h <= height:
        return (
            f"; a window (crop) of the detector? give a nominal for the window (image_size_px [{w}, {h}], the "
            "principal point less the window's first column and row), or the parameter file of this camera"
        )
    return "; the parameter file does not describe this camera"


def check_on_detector(session: Session, image_size_px: tuple[int, int], session_name: str, params_name: str) -> None:
    """Refuse (one-line UserError) a session measured in images of another size than the detector of a parameter
    file (:data:`IMAGE_SIZE_COLUMNS`, where the session records it: rows without it are not checked so), and a
    session with a centroid off that detector (``[-0.5, w - 0.5] x [-0.5, h - 0.5]``, docs/camera-model.md, plus
    :data:`DETECTOR_MARGIN_PX`): the file then describes another camera and every result would be silently wrong.
    The sizes must be equal: a flipped or 180-deg rotated image keeps its size, a turned or binned one is another
    detector (:func:`image_size_mismatch` says which)."""
    width, height = (int(v) for v in image_size_px)
    sizes = image_sizes_px(session)
    if sizes is not None:
        known = (sizes[:, 0] > 0) & (sizes[:, 1] > 0)
        other = known & ((sizes[:, 0] != width) | (sizes[:, 1] != height))
        if np.any(other):
            k = int(np.argmax(other))
            w, h = int(sizes[k, 0]), int(sizes[k, 1])
            raise UserError(
                f"{session_name}: its images are {w} x {h} px (frame {int(session.frame[k])}) but the detector of "
                f"{params_name} is {width} x {height} px{image_size_mismatch((w, h), (width, height))}"
            )
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
