"""The frames of a calibration as chunks: what a pass over the data reads, one chunk in memory at a time."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.data import MIN_STARS_PER_FRAME, CalibrationData


def frames_of(data: CalibrationData, f0: int, f1: int) -> CalibrationData:
    """The frames [f0, f1) of ``data`` as a CalibrationData of their own (views, no copy)."""
    a, b = int(data.frame_starts[f0]), int(data.frame_starts[f1])
    return CalibrationData(
        data.x_px[a:b],
        data.y_px[a:b],
        data.r[a:b],
        data.frame_starts[f0 : f1 + 1] - a,
        data.frame_number[f0:f1],
        data.star_id[a:b],
        data.source_rows()[a:b],
        None if data.sigma_px is None else data.sigma_px[a:b],
    )


def without_rows(data: CalibrationData, excluded_rows: np.ndarray) -> CalibrationData:
    """``data`` less the stars whose source row is in the sorted array ``excluded_rows``, and less the frames left
    with fewer than :data:`hostlink.calibration.data.MIN_STARS_PER_FRAME` stars."""
    rows = data.source_rows()
    keep = None
    if excluded_rows.size:
        pos = np.minimum(np.searchsorted(excluded_rows, rows), excluded_rows.size - 1)
        keep = excluded_rows[pos] != rows
        if np.all(keep):
            keep = None
    if keep is None and np.all(data.counts >= MIN_STARS_PER_FRAME):
        return data  # nothing to leave out: the data themselves, not a copy (callers only read them)
    return data.select(np.ones(data.n_obs, dtype=bool) if keep is None else keep)[0]


@dataclass(frozen=True)
class ChunkSource:
    """The frames of a calibration as chunks (whole frames, each with its source rows): ``handles`` are what
    ``load`` turns into a :class:`CalibrationData` (the data itself in memory, a spool file on disk), so a pass
    can run where the handle is (:mod:`hostlink.calibration.distributed`)."""

    handles: tuple
    load: Callable[[object], CalibrationData] | None = None
    #: the number of frames of a handle's chunk without loading all of it (None: load the chunk and count)
    count: Callable[[object], int] | None = None
    #: the chunk loaded last, kept until another one is loaded (memory: one chunk), so the passes over a session of
    #: one chunk read it once (the chunks are read-only: every pass selects copies)
    _last: list = field(default_factory=list, compare=False, repr=False)

    def chunk(self, handle: object) -> CalibrationData:
        if self.load is None:
            return handle
        if self._last and self._last[0] == handle:
            return self._last[1]
        self._last.clear()  # the previous chunk is released before the next one is read
        data = self.load(handle)
        self._last.extend((handle, data))
        return data

    def n_frames(self) -> int:
        """Frames in all the chunks."""
        if self.load is None:
            return sum(h.n_frames for h in self.handles)
        return sum(self.count(h) if self.count is not None else self.load(h).n_frames for h in self.handles)

    def __iter__(self):
        return (self.chunk(h) for h in self.handles)


def in_memory_source(data: CalibrationData) -> ChunkSource:
    """``data`` as a one-chunk source (the in-memory path: the same passes, one chunk)."""
    return ChunkSource((data,))
