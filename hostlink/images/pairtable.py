"""The own matcher's table of catalogue pairs sorted by angle, as :func:`hostlink.images.skyindex.pair_catalogue`
builds it and :func:`hostlink.images.skyindex.pair_window` reads it: the pairs found group by group of the stars and
staged in blocks (:func:`find_pairs`, :class:`_PairBlocks`), sorted bucket by bucket of angle (:func:`sorted_pairs`)
and kept as their two stars (int32, 8 bytes a pair) with the angle of every :data:`ANGLE_SAMPLE_PAIRS`-th pair; the
angles between two samples are computed again where a search needs them (:func:`angle_index`), the same arccos of the
same sums (:func:`pair_angles`), so that every search finds what a search of all the angles finds. The build's peak
is its staging (9 bytes a pair), not several times the table (docs/realsky.md, "The own matcher's pair table:
memory")."""

from __future__ import annotations

import numpy as np

#: The table keeps the angle of every this-many-th pair [pairs]: a search computes at most this many angles again.
ANGLE_SAMPLE_PAIRS = 64
#: :func:`find_pairs` finds the pairs group by group of the stars taking part (in sky order, which follows right
#: ascension; each group with its own k-d tree: the pairs within a group, then with each later group, once each) ...
PAIR_BUILD_STAR_GROUPS = 32
#: ... stages them in blocks of this many pairs (9 bytes a pair: a, b and the angle's bucket), each block its own
#: anonymous memory map, unmapped as soon as its pairs are in the table (freed numpy arrays of a few MB may stay with
#: the allocator instead of going back to the system) ...
PAIR_BUILD_BLOCK_PAIRS = 1 << 20
#: ... and :func:`sorted_pairs` sorts them bucket by bucket of angle, the buckets of about equal counts (a pair's
#: angle on a uniform sky has a density proportional to it for small angles: edges at max_angle * sqrt(k / N)).
PAIR_BUILD_ANGLE_BUCKETS = 64


def sky_columns(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The columns x, y, z of unit vectors ``r`` (S, 3), each contiguous (:func:`_dot_rows`)."""
    x, y, z = (np.ascontiguousarray(r[:, axis]) for axis in range(3))
    return x, y, z


def _dot_rows(columns: tuple[np.ndarray, np.ndarray, np.ndarray], i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """r[i] . r[j] row by row from the columns of r (:func:`sky_columns`), x + y + z summed axis by axis (no (M, 3)
    gathers, which cost many times more: docs/realsky.md, "Figures behind the speed choices"), (x + y) + z as a sum
    over the 3 components of each row adds them: the same angles for :func:`pair_angles`; another summation
    order would differ in the last bit, which :func:`hostlink.images.matcher._pyramid_may_hit` could afford (its
    bounds are twice the hit chord from any hit)."""
    x, y, z = columns
    return x[i] * x[j] + y[i] * y[j] + z[i] * z[j]


def pair_angles(columns: tuple[np.ndarray, np.ndarray, np.ndarray], a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angles [rad] between the sky's stars ``a`` and ``b`` (index arrays): arccos of the clipped dot product,
    elementwise, so that a pair's angle is the same bits whatever array it is computed in."""
    return np.arccos(np.clip(_dot_rows(columns, a, b), -1.0, 1.0))


def angle_index(
    samples: np.ndarray,
    columns: tuple[np.ndarray, np.ndarray, np.ndarray],
    a: np.ndarray,
    b: np.ndarray,
    angle_rad: float,
    side: str = "left",
) -> int:
    """``np.searchsorted(angles, angle_rad, side)`` over the angles of the pairs (``a``, ``b``) in ascending order,
    of which ``samples`` holds every :data:`ANGLE_SAMPLE_PAIRS`-th: the samples bracket the index, and the angles
    between the two are computed again (:func:`pair_angles`)."""
    k = int(np.searchsorted(samples, angle_rad, side=side))  # the index lies in ((k - 1) K, k K]
    if k == 0:
        return 0
    lo = (k - 1) * ANGLE_SAMPLE_PAIRS + 1
    hi = min(k * ANGLE_SAMPLE_PAIRS, a.size)
    return lo + int(np.searchsorted(pair_angles(columns, a[lo:hi], b[lo:hi]), angle_rad, side=side))


def find_pairs(points: np.ndarray, rows: np.ndarray, chord: float, columns, edges: np.ndarray) -> list[tuple]:
    """The pairs of ``points`` (the unit vectors of the sky's stars ``rows``, ascending) within ``chord``, each once,
    staged (:class:`_PairBlocks`; ``edges``: the angle buckets' inner bounds [rad]): ``query_pairs`` within each of
    :data:`PAIR_BUILD_STAR_GROUPS` groups of the stars, ``sparse_distance_matrix`` between groups (``scipy.spatial``
    ``cKDTree``; the same pairs as ``query_pairs`` over all the stars at once)."""
    from scipy.spatial import cKDTree

    staged = _PairBlocks(rows, columns, edges)
    bounds = np.linspace(0, rows.size, PAIR_BUILD_STAR_GROUPS + 1).astype(np.int64)
    trees = [cKDTree(points[lo:hi]) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    for g, group in enumerate(trees):
        within = group.query_pairs(chord, output_type="ndarray")
        staged.add(bounds[g] + within[:, 0], bounds[g] + within[:, 1])
        del within
        for h in range(g + 1, len(trees)):
            across = group.sparse_distance_matrix(trees[h], chord, output_type="ndarray")
            staged.add(bounds[g] + across["i"], bounds[h] + across["j"])
    return staged.filled()


class _PairBlocks:
    """Pairs staged in blocks of :data:`PAIR_BUILD_BLOCK_PAIRS`, each an anonymous memory map holding (a, b, bucket):
    a < b int32 sky indices and the bucket (uint8) of their angle (:func:`pair_angles`) among ``edges``.
    :meth:`filled`: [(a, b, bucket)], views of their maps, filled to their length."""

    def __init__(self, rows: np.ndarray, columns, edges: np.ndarray) -> None:
        self.rows, self.columns, self.edges = rows, columns, edges
        self.blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._free = 0

    def _new_block(self) -> None:
        import mmap

        n = PAIR_BUILD_BLOCK_PAIRS
        buffer = mmap.mmap(-1, 9 * n)
        layout = ((np.int32, 0), (np.int32, 4 * n), (np.uint8, 8 * n))
        self.blocks.append(tuple(np.frombuffer(buffer, dtype, n, offset) for dtype, offset in layout))
        self._free = n

    def add(self, i: np.ndarray, j: np.ndarray) -> None:
        """The pairs (rows[i], rows[j]) (i < j), a block's free space at a time."""
        start = 0
        while start < i.size:
            if self._free == 0:
                self._new_block()
            stop = min(i.size, start + self._free)
            a = self.rows[i[start:stop]].astype(np.int32)
            b = self.rows[j[start:stop]].astype(np.int32)
            at = PAIR_BUILD_BLOCK_PAIRS - self._free
            at = slice(at, at + a.size)
            block = self.blocks[-1]
            block[0][at], block[1][at] = a, b
            block[2][at] = np.searchsorted(self.edges, pair_angles(self.columns, a, b), side="right")
            self._free -= a.size
            start = stop

    def filled(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The blocks, the last cut to its pairs (views of the same map: it is unmapped when the last one goes)."""
        if self.blocks and self._free:
            self.blocks[-1] = tuple(column[: PAIR_BUILD_BLOCK_PAIRS - self._free] for column in self.blocks[-1])
            self._free = 0
        return self.blocks


def _small_paged(n: int, dtype) -> np.ndarray:
    """An uninitialised (n,) array of ``dtype`` in its own anonymous memory map, advised against transparent huge
    pages where the system has them (``MADV_NOHUGEPAGE``): :func:`sorted_pairs` writes each block's pairs into all
    the buckets' parts of the table at once, and numpy's own large arrays ask for 2 MB pages, each resident from its
    first byte written (+135 MB for a 150 MB table after its first block, measured) instead of as it fills."""
    import mmap

    nbytes = n * np.dtype(dtype).itemsize
    if nbytes == 0:
        return np.empty(0, dtype=dtype)
    buffer = mmap.mmap(-1, nbytes)
    if hasattr(mmap, "MADV_NOHUGEPAGE"):
        buffer.madvise(mmap.MADV_NOHUGEPAGE)
    return np.frombuffer(buffer, dtype, n)


def sorted_pairs(blocks: list[tuple], n_buckets: int, columns) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The staged pairs (:func:`find_pairs`) as the table (a, b, samples) in (angle, a, b) order: each block's pairs
    put into their bucket's part of the table and the block freed (``blocks`` is emptied), then each bucket's angles
    computed (:func:`pair_angles`) and sorted (any sort by angle, its runs of equal angles then put in (a, b) order,
    whatever order the sort left them in: :func:`_ties_by_stars`); samples: the angle of every
    :data:`ANGLE_SAMPLE_PAIRS`-th pair [rad]."""
    counts = sum((np.bincount(block[2], minlength=n_buckets) for block in blocks), np.zeros(n_buckets, np.int64))
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    total = int(starts[-1])
    a, b = _small_paged(total, np.int32), _small_paged(total, np.int32)
    cursor = starts[:-1].copy()
    while blocks:
        ak, bk, bucket = blocks.pop(0)
        order = np.argsort(bucket, kind="stable")
        ends = np.searchsorted(bucket[order], np.arange(1, n_buckets + 1), side="left")
        for k, part in enumerate(np.split(order, ends[:-1])):
            at = slice(cursor[k], cursor[k] + part.size)
            a[at], b[at] = ak[part], bk[part]
            cursor[k] += part.size
        del ak, bk, bucket, order  # the block's map goes with its last view
    samples = np.empty(-(-total // ANGLE_SAMPLE_PAIRS), dtype=np.float64)
    for lo, hi in zip(starts[:-1], starts[1:], strict=True):
        if hi > lo:
            ak, bk = a[lo:hi], b[lo:hi]
            angle = pair_angles(columns, ak, bk)
            order = _ties_by_stars(np.argsort(angle), angle, ak, bk)
            a[lo:hi], b[lo:hi], angle = ak[order], bk[order], angle[order]
            first = -(-lo // ANGLE_SAMPLE_PAIRS) * ANGLE_SAMPLE_PAIRS  # the first sampled pair of the bucket
            if first < hi:
                at = slice(first // ANGLE_SAMPLE_PAIRS, (hi - 1) // ANGLE_SAMPLE_PAIRS + 1)
                samples[at] = angle[first - lo :: ANGLE_SAMPLE_PAIRS]
    return a, b, samples


def _ties_by_stars(order: np.ndarray, angle: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``order`` (ascending ``angle``) with every run of equal angles reordered by (a, b) (one in 13 million pairs
    to Hp 8.7 within 8.8 deg)."""
    ordered = angle[order]
    tied = np.flatnonzero(ordered[1:] == ordered[:-1])
    if tied.size == 0:
        return order
    out = order.copy()
    starts = tied[np.concatenate([[True], np.diff(tied) > 1])]
    for start in starts:
        stop = start + 1
        while stop < order.size and angle[order[stop]] == angle[order[start]]:
            stop += 1
        run = order[start:stop]
        out[start:stop] = run[np.lexsort((b[run], a[run]))]
    return out
