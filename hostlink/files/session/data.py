"""The session in memory (docs/file-formats.md): the :class:`Session` columns and their frames, selecting and joining
rows, and the check that a session belongs to a camera's detector."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from hostlink.errors import UserError
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
