"""The observations a batch calibration works on: measured centroids and their reference directions, by frame.

Everything is float64 numpy columns, one row per identified star, rows grouped by frame. Frames are numbered
0..M-1 internally; ``frame_number`` keeps the session's frame counter for reports.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session, cell_numbers
from onboard.params import MAX_IMAGE_SIDE_PX
from onboard.site import Site, Weather

if TYPE_CHECKING:
    from hostlink.sky.references import SessionReferences

#: A frame needs at least this many stars to say anything about the camera beyond its attitude (3 attitude
#: parameters take 2 stars; a third star is the first that constrains the camera and lets an outlier show).
MIN_STARS_PER_FRAME = 3


@dataclass(frozen=True)
class CalibrationData:
    """Observations grouped by frame.

    x_px, y_px: measured centroids [px] (docs/camera-model.md pixel convention), shape (N,).
    r: reference unit vectors (N, 3) in the frame the attitude maps from (b = C r).
    frame_starts: (M + 1,) row index where each frame starts, last entry N.
    frame_number: (M,) session frame counter of each frame.
    star_id: (N,) Hipparcos numbers (0 if unknown).
    row: (N,) the row of each star in the session it came from (for reports of rejected stars); default 0..N-1.
    sigma_px: (N,) each star's 1-sigma centroid noise per axis [px] (the session's optional ``sigma_px`` column),
    or None: the same unknown noise for every star. Given, the bundle weights each star by it (whitening).
    """

    x_px: np.ndarray
    y_px: np.ndarray
    r: np.ndarray
    frame_starts: np.ndarray
    frame_number: np.ndarray
    star_id: np.ndarray
    row: np.ndarray | None = None
    sigma_px: np.ndarray | None = None

    @property
    def n_obs(self) -> int:
        return int(self.x_px.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.frame_starts.shape[0] - 1)

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.frame_starts)

    def source_rows(self) -> np.ndarray:
        """(N,) session row of each star (:attr:`row`, or 0..N-1 when the data did not come from a session)."""
        return np.arange(self.n_obs, dtype=np.int64) if self.row is None else self.row

    def frame_index(self) -> np.ndarray:
        """(N,) internal frame index of each row."""
        return np.repeat(np.arange(self.n_frames, dtype=np.int64), self.counts)

    def select(
        self, keep: np.ndarray, min_stars: int = MIN_STARS_PER_FRAME
    ) -> tuple[CalibrationData, np.ndarray, np.ndarray]:
        """Rows where ``keep`` is true, dropping frames left with fewer than ``min_stars``.

        Returns the new data, the (N,) mask of rows kept and the (M,) mask of frames kept from this one.
        """
        keep = np.asarray(keep, dtype=bool).copy()
        counts = self.counts
        cum = np.zeros(self.n_obs + 1, dtype=np.int64)
        np.cumsum(keep, out=cum[1:])
        per_frame = cum[self.frame_starts[1:]] - cum[self.frame_starts[:-1]]
        frame_kept = per_frame >= min_stars
        if not np.all(frame_kept):
            keep &= np.repeat(frame_kept, counts)
        present = frame_kept & (per_frame > 0)  # the frames of the result (those with rows left)
        starts = np.zeros(int(np.count_nonzero(present)) + 1, dtype=np.int64)
        np.cumsum(per_frame[present], out=starts[1:])
        rows = np.flatnonzero(keep)
        # np.take rather than indexing: the same rows, gathered several times faster for the (N, 3) vectors
        new = CalibrationData(
            x_px=np.asarray(np.take(self.x_px, rows), dtype=np.float64),
            y_px=np.asarray(np.take(self.y_px, rows), dtype=np.float64),
            r=np.asarray(np.take(np.asarray(self.r).reshape(-1, 3), rows, axis=0), dtype=np.float64),
            frame_starts=starts,
            frame_number=np.asarray(np.asarray(self.frame_number)[present], dtype=np.int64),
            star_id=np.asarray(np.take(self.star_id, rows), dtype=np.int64),
            row=np.asarray(np.take(self.source_rows(), rows), dtype=np.int64),
            sigma_px=None if self.sigma_px is None else np.take(self.sigma_px, rows),
        )
        return new, keep, frame_kept


def take_frames(data: CalibrationData, frames: np.ndarray) -> CalibrationData:
    """The frames of ``data`` at the sorted, unique int64 indices ``frames`` (those without a star left out) as a data
    set of their own, gathered by row ranges: ``data.select`` of their rows with ``min_stars=1`` (for float64 data),
    without a mask over every row."""
    counts = data.counts[frames]
    frames = frames[counts > 0]
    counts = counts[counts > 0]
    starts = np.zeros(frames.size + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    rows = np.arange(int(starts[-1]), dtype=np.int64) + np.repeat(data.frame_starts[frames] - starts[:-1], counts)
    return CalibrationData(
        x_px=np.take(data.x_px, rows),
        y_px=np.take(data.y_px, rows),
        r=np.take(data.r, rows, axis=0),
        frame_starts=starts,
        frame_number=np.asarray(data.frame_number, dtype=np.int64)[frames],
        star_id=np.take(np.asarray(data.star_id, dtype=np.int64), rows),
        row=np.take(data.source_rows(), rows).astype(np.int64, copy=False),
        sigma_px=None if data.sigma_px is None else np.take(data.sigma_px, rows),
    )


def build_data(
    x_px: np.ndarray,
    y_px: np.ndarray,
    r: np.ndarray,
    frame_key: np.ndarray,
    frame_number: np.ndarray | None = None,
    star_id: np.ndarray | None = None,
    row: np.ndarray | None = None,
    sigma_px: np.ndarray | None = None,
) -> CalibrationData:
    """Group rows (already in frame order) into frames by consecutive equal ``frame_key``.

    ``frame_number`` (indexed by frame_key) gives the session frame counter; default the key itself. ``row``: the
    session row of each star (default 0..N-1); ``sigma_px``: each star's centroid noise [px] (None: not known).
    """
    frame_key = np.asarray(frame_key, dtype=np.int64)
    n = frame_key.shape[0]
    if n:
        change = np.flatnonzero(np.diff(frame_key) != 0) + 1
        starts = np.concatenate([[0], change, [n]]).astype(np.int64)
        keys = frame_key[starts[:-1]]
    else:
        starts = np.zeros(1, dtype=np.int64)
        keys = np.zeros(0, dtype=np.int64)
    numbers = keys if frame_number is None else np.asarray(frame_number)[keys]
    return CalibrationData(
        x_px=np.asarray(x_px, dtype=np.float64),
        y_px=np.asarray(y_px, dtype=np.float64),
        r=np.asarray(r, dtype=np.float64).reshape(-1, 3),
        frame_starts=starts,
        frame_number=np.asarray(numbers, dtype=np.int64),
        star_id=np.zeros(n, dtype=np.int64) if star_id is None else np.asarray(star_id, dtype=np.int64),
        row=np.arange(n, dtype=np.int64) if row is None else np.asarray(row, dtype=np.int64),
        sigma_px=None if sigma_px is None else np.asarray(sigma_px, dtype=np.float64),
    )


def calibration_data_from_session(
    session: Session, site: Site | None = None, weather: Weather | None = None, dut1_s: float = 0.0
) -> tuple[CalibrationData, SessionReferences]:
    """The identified rows of a session as :class:`CalibrationData` (frames with at least
    :data:`MIN_STARS_PER_FRAME` identified stars), with their reference directions from the one service
    (:func:`hostlink.sky.references.session_references`: file or Hipparcos; with ``site`` as observed there, with
    ``weather`` also refracted; ``dut1_s`` = UT1 - UTC [s]; star ids Hipparcos does not have are skipped and
    listed in the report) and its report of where they came from. Raises
    :class:`UserError` when no star is identified or no frame has enough of them."""
    if not np.any(session.star_id != 0):
        raise UserError("the session has no identified star (every star_id is 0)")
    data, references = session_chunk_data(session, site, weather, dut1_s)
    unknown = references.unknown_rows
    if not np.any(references.usable) and unknown.size:
        raise UserError(
            f"no identified star is in the Hipparcos catalogue ({unknown.size} unknown star_id, first "
            f"{int(session.star_id[unknown[0]])} on line {int(unknown[0]) + 2})"
        )
    if data.n_frames == 0:
        raise UserError(f"no frame has at least {MIN_STARS_PER_FRAME} identified stars")
    return data, references


def session_chunk_data(
    session: Session,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    row_offset: int = 0,
) -> tuple[CalibrationData, SessionReferences]:
    """:func:`calibration_data_from_session` for one chunk of a session (whole frames), without its checks: the
    data may be empty. Source rows are the chunk's rows plus ``row_offset`` (the rows of the chunks before it)."""
    from hostlink.sky.references import session_references

    references = session_references(session, site, weather, dut1_s, skip_unknown_ids=True)
    rows = np.flatnonzero(references.usable)
    sub = session.select(rows)
    sigma = session_sigma_px(sub, rows + row_offset)
    data = build_data(sub.x_px, sub.y_px, references.r[rows], sub.frame, None, sub.star_id, rows + row_offset, sigma)
    data, _, _ = data.select(np.ones(data.n_obs, dtype=bool))
    return data, references


#: The arrays of a spooled chunk (:func:`save_chunk`), in the order they are written: the frame starts first, so the
#: frame count is read without the rest (:func:`chunk_frame_count`); ``sigma_px`` empty when the session has none.
SPOOL_FIELDS = ("frame_starts", "frame_number", "x_px", "y_px", "r", "star_id", "row", "sigma_px")
#: The file name suffix of a spooled chunk.
SPOOL_SUFFIX = ".spool"


def save_chunk(path: Path, data: CalibrationData) -> None:
    """Write one chunk of calibration data to ``path``: its arrays (:data:`SPOOL_FIELDS`) as numpy ``.npy``
    records one after the other in one file, nothing around them, so :func:`load_chunk` reads them at disk speed (a
    member of an ``.npz`` archive is also checksummed as it is read, which costs about as much as the read)."""
    arrays = {name: getattr(data, name) for name in SPOOL_FIELDS if name not in ("row", "sigma_px")}
    arrays["row"] = data.source_rows()
    arrays["sigma_px"] = np.zeros(0) if data.sigma_px is None else data.sigma_px
    from hostlink.files.atomic import atomic_open

    with atomic_open(path, binary=True, durable=False) as f:  # scratch: never fsync-ed, never through a link
        for name in SPOOL_FIELDS:
            np.save(f, np.ascontiguousarray(arrays[name]), allow_pickle=False)


def load_chunk(path: str | Path) -> CalibrationData:
    """A chunk written by :func:`save_chunk` (also one written without the last record, ``sigma_px``, as chunks were
    before it). Raises ValueError naming the file when it is not one (cut short, with data after its arrays, or
    arrays that do not fit together)."""
    try:
        with open(path, "rb") as f:
            arrays = {name: np.load(f, allow_pickle=False) for name in SPOOL_FIELDS[:-1]}
            # sigma_px, the last record, is absent from chunks spooled before it existed: read as none
            at = f.tell()
            arrays["sigma_px"] = np.zeros(0)
            if f.read(1):
                f.seek(at)
                arrays["sigma_px"] = np.load(f, allow_pickle=False)
            trailing = f.read(1)
    except (OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{path}: not a spooled calibration chunk ({exc})") from exc
    if not all(isinstance(a, np.ndarray) and a.ndim >= 1 for a in arrays.values()):
        raise ValueError(f"{path}: not a spooled calibration chunk (an archive or a scalar where an array belongs)")
    starts, n = arrays["frame_starts"], arrays["x_px"].shape[0]
    fits = (
        not trailing
        and starts.ndim == 1
        and starts.size >= 1
        and int(starts[0]) == 0
        and int(starts[-1]) == n
        and arrays["frame_number"].shape == (starts.size - 1,)
        and arrays["r"].shape == (n, 3)
        and all(arrays[name].shape == (n,) for name in ("y_px", "star_id", "row"))
        and arrays["sigma_px"].shape in ((n,), (0,))
    )
    if not fits:
        raise ValueError(f"{path}: not a spooled calibration chunk (its arrays do not fit together)")
    if arrays["sigma_px"].size == 0:
        arrays["sigma_px"] = None
    return CalibrationData(**arrays)


def chunk_frame_count(path: str | Path) -> int:
    """The number of frames of a chunk written by :func:`save_chunk`, reading only its frame starts."""
    with open(path, "rb") as f:
        return int(np.load(f, allow_pickle=False).size - 1)


def concatenate_data(parts: list[CalibrationData]) -> CalibrationData:
    """Data sets of consecutive frames joined into one (frames and source rows kept as they are)."""
    if not parts:
        return build_data(np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    starts, offset = [np.zeros(1, dtype=np.int64)], 0
    for p in parts:
        starts.append(p.frame_starts[1:] + offset)
        offset += p.n_obs
    return CalibrationData(
        np.concatenate([p.x_px for p in parts]),
        np.concatenate([p.y_px for p in parts]),
        np.concatenate([p.r for p in parts]),
        np.concatenate(starts),
        np.concatenate([p.frame_number for p in parts]),
        np.concatenate([p.star_id for p in parts]),
        np.concatenate([p.source_rows() for p in parts]),
        _joined_sigma([p.sigma_px for p in parts]),
    )


def _joined_sigma(parts: list[np.ndarray | None]) -> np.ndarray | None:
    """The stars' noise of joined data sets: None when none has it (the parts of one session all have it or not)."""
    if all(p is None for p in parts):
        return None
    if any(p is None for p in parts):
        raise ValueError("data sets with and without per-star sigma_px cannot be joined")
    return np.concatenate(parts)


#: Largest full well of a detector pixel [electrons]: scientific CCDs reach a few 10^5, the deepest ~10^6.
_MAX_FULL_WELL_E = 1.0e6
#: Smallest 1-sigma centroid noise per axis a single exposure reaches [px]: the photon-noise Cramer-Rao bound of a
#: Gaussian PSF of width s and N electrons is s / sqrt(N) (King 1983, PASP 95, 163; Mendez et al. 2013, PASP 125,
#: 580), and an unsaturated star holds N <= 2 pi s^2 W (its peak pixel, N / (2 pi s^2), below the full well W), so
#: sigma >= 1 / sqrt(2 pi W) whatever the PSF's width: 4.0e-4 px at W = 10^6 e-. A smaller stated noise (a bound
#: that left out the star's shot noise, or a unit mistake) is taken as this floor: believed as given, one star of
#: 1e-9 px would outweigh every other by 10^16 and overflow the weighted fit.
SIGMA_PX_FLOOR = 1.0 / float(np.sqrt(2.0 * np.pi * _MAX_FULL_WELL_E))
#: Largest stated centroid noise [px]: the largest detector side the project reads (``onboard.params``
#: MAX_IMAGE_SIDE_PX, 2**24); a larger "noise" says nothing about a position on any detector (a column in other
#: units) and is refused.
SIGMA_PX_CEILING = float(MAX_IMAGE_SIDE_PX)


def session_sigma_px(session: Session, rows: np.ndarray) -> np.ndarray | None:
    """The stars' 1-sigma centroid noise per axis [px] from the session's optional ``sigma_px`` column (a typed
    field where the reader gives one, else the column kept as text), or None without it. ``rows``: the stars' session
    rows, for the error. Raises :class:`UserError` (one line, naming the file line and column) for a value that is
    not a finite number of pixels in (0, :data:`SIGMA_PX_CEILING`]; a positive value below :data:`SIGMA_PX_FLOOR`
    (the photon-noise limit of any single exposure) is taken as the floor."""
    typed = getattr(session, "sigma_px", None)
    raw = typed if typed is not None else session.extra.get("sigma_px")
    if raw is None:
        return None
    values = cell_numbers(raw)
    bad = np.flatnonzero(~(np.isfinite(values) & (values > 0) & (values <= SIGMA_PX_CEILING)))
    if bad.size:
        k = int(bad[0])
        raise UserError(
            f"sigma_px on line {int(rows[k]) + 2}: {raw[k]!r}: expected a positive number of pixels up to "
            f"{SIGMA_PX_CEILING:.0f} (the star's 1-sigma centroid noise per axis)"
        )
    return np.maximum(values, SIGMA_PX_FLOOR)


def frame_chunks(frame_starts: np.ndarray, max_obs: int) -> list[tuple[int, int]]:
    """Split frames into consecutive chunks [f0, f1) of at most ``max_obs`` rows (a frame is never split; a single
    frame larger than ``max_obs`` is a chunk of its own). Bounds the working memory of every pass over the data."""
    m = frame_starts.shape[0] - 1
    chunks = []
    f0 = 0
    while f0 < m:
        f1 = int(np.searchsorted(frame_starts, frame_starts[f0] + max_obs, side="right")) - 1
        f1 = min(max(f1, f0 + 1), m)
        chunks.append((f0, f1))
        f0 = f1
    return chunks


def frame_blocks(frame_starts: np.ndarray, max_obs: int) -> list[np.ndarray]:
    """The frames in blocks of at most ``max_obs`` rows (a frame is never split; one larger than ``max_obs`` is a
    block of its own), ordered by star count (stable) rather than in time: the frames of a block have about the
    same count, so the per-frame layouts padded to a block's largest count (Gram matrices, per-frame products)
    carry almost no padding (for 10-30 stars per frame, half the padded entries of :func:`frame_chunks`' blocks).
    Returns each block's frame indices."""
    counts = np.diff(frame_starts)
    order = np.argsort(counts, kind="stable")
    cum = np.cumsum(counts[order])
    blocks, start, done = [], 0, 0
    while start < order.size:
        end = max(int(np.searchsorted(cum, done + max_obs, side="right")), start + 1)
        blocks.append(order[start:end])
        done, start = int(cum[end - 1]), end
    return blocks


def count_blocks(frame_starts: np.ndarray, max_obs: int) -> Iterator[tuple[np.ndarray, int, int]]:
    """The frames of :func:`frame_blocks`, each block split by star count: for every count n of a block, the rows
    (m n,) of its m frames of n stars, frame by frame (so an (m, n, 3) stack of their vectors is a reshape, without
    padding), with m and n."""
    counts = np.diff(frame_starts)
    for frames in frame_blocks(frame_starts, max_obs):
        for n in np.unique(counts[frames]):
            same = frames[counts[frames] == n]
            yield (frame_starts[same][:, None] + np.arange(n)).ravel(), int(same.size), int(n)


def block_gram(v: np.ndarray, rows: np.ndarray, m: int, n: int) -> np.ndarray:
    """The Gram matrices (m, n n), flattened row by row, of the vectors of ``v`` (N, 3) at the rows of m frames of n
    stars (:func:`count_blocks`): every pair's dot product; the pairs i < j of each frame are the flat positions
    i n + j of ``np.triu_indices(n, 1)``."""
    return gram_matrices(np.take(v, rows, axis=0).reshape(m, n, 3)).reshape(m, n * n)


def measured_directions(data: CalibrationData, theta: np.ndarray, max_obs: int = 50_000) -> np.ndarray:
    """Sensor-frame unit vectors (N, 3) of every centroid through the camera ``theta`` (``onboard.camera``),
    computed a chunk at a time so the temporaries stay bounded."""
    from onboard.camera import pixels_to_unit

    out = np.empty((data.n_obs, 3))
    for a in range(0, data.n_obs, max_obs):
        z = min(a + max_obs, data.n_obs)
        out[a:z] = pixels_to_unit(data.x_px[a:z], data.y_px[a:z], theta)
    return out


def frame_slots(frame_starts: np.ndarray, f0: int, f1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Where the rows of frames [f0, f1) go in a layout of (m, nmax, ...) arrays padded to the frames' largest star
    count (per-frame pair computations vectorise): (rows, frame, slot, nmax), the data rows, each row's frame
    (0 = f0) and slot in it (its star's position in the frame), and the largest star count (the padded width)."""
    counts = np.diff(frame_starts[f0 : f1 + 1])
    nmax = int(counts.max(initial=0))
    rows = int(frame_starts[f0]) + np.arange(int(frame_starts[f1] - frame_starts[f0]))
    frame = np.repeat(np.arange(f1 - f0), counts)
    slot = rows - np.repeat(frame_starts[f0:f1], counts)
    return rows, frame, slot, nmax


def angle_from_dot_rad(dot: np.ndarray) -> np.ndarray:
    """The angle [rad] between two unit vectors from their dot product, through the chord sqrt(2 - 2 a.b) (accurate
    at small angles, where arccos is not): twice :func:`half_angle_from_dot_rad`. Monotone: the largest angle is
    that of the smallest dot product."""
    x = half_angle_from_dot_rad(dot)
    x *= 2.0
    return x


def half_angle_from_dot_rad(dot: np.ndarray) -> np.ndarray:
    """Half the angle [rad] between two unit vectors from their dot product: arcsin of the half chord
    sqrt((1 - a.b) / 2) (= sqrt(2 - 2 a.b) / 2 exactly: the scalings are by powers of two), clipped to [0, 1]
    (rounding can put a.b just outside [-1, 1]). A new array, also of a scalar (0-d, writable); computed in place
    on it."""
    x = np.asarray(np.subtract(1.0, dot, dtype=np.float64))
    x *= 0.5
    np.clip(x, 0.0, 1.0, out=x)  # the square of the half chord: clipped before the root, the same numbers as after
    np.sqrt(x, out=x)
    np.arcsin(x, out=x)
    return x


def gram_matrices(v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The Gram matrices v v^T (m, n, n) of stacked padded frames ``v`` (m, n, 3): every dot product between two of
    a frame's vectors. The transposed factor is a contiguous copy, so numpy calls BLAS gemm rather than syrk (its
    choice for v @ v^T of one buffer): the same three-term dot products, faster for these thin factors (OpenBLAS;
    docs/calibration.md, "Figures behind the constants"). On one BLAS thread (:func:`one_blas_thread`): each product
    is a few milliseconds at most, and OpenBLAS's threads spend more waiting than computing (the same numbers: each
    entry is one thread's three-term dot product either way). ``out``: an (m, n, n) buffer to reuse."""
    with one_blas_thread():
        return np.matmul(v, np.ascontiguousarray(v.transpose(0, 2, 1)), out=out)


def _blas_controller():
    """The process's thread-pool controller (threadpoolctl), found again whenever a module was imported since the
    last call (a BLAS library, scipy's for one, is loaded by an import; a controller made before it would not hold
    it to one thread), else reused (each controller scans the loaded libraries)."""
    return _blas_controller_of(len(sys.modules))


@functools.lru_cache(maxsize=1)
def _blas_controller_of(n_modules: int):
    """The thread-pool controller made while ``n_modules`` modules were imported (:func:`_blas_controller`)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def one_blas_thread():
    """A context in which BLAS runs on one thread (the previous limit restored on exit): for code whose matrix
    products are thin (N x 3 by 3 x 3, per-frame Gram matrices), which OpenBLAS would spread over threads that
    spend more time synchronising than computing (docs/calibration.md, "Figures behind the constants"). The limit is
    the process's (OpenBLAS keeps one): threads that enter and leave this at once can leave it at one thread, which
    only slows large products elsewhere in the process."""
    return _blas_controller().limit(limits=1, user_api="blas")


def pair_angles_at_rad(v: np.ndarray, positions: np.ndarray, gram: np.ndarray | None = None) -> np.ndarray:
    """Angles [rad] between the vectors of the pairs at flat ``positions`` (frame by frame, row-major) in the Gram
    matrices (:func:`gram_matrices`) of the padded frames ``v`` (m, n, 3), in that order, from the chord
    |a - b|^2 = 2 - 2 a.b (:func:`angle_from_dot_rad`). In float64 the angle's error is ~1e-16 / angle rad (1e-13
    rad at 1 mrad), far below the voting tolerance and the interstar RMS of any real sensor; a batched matrix
    product keeps it fast, and only the real pairs get an arcsine. ``gram``: an (m, n, n) buffer to reuse."""
    return angle_from_dot_rad(gram_matrices(v, gram).reshape(-1)[positions])
