"""Order statistics of many rows at once, numpy's own numbers bit for bit: ``np.percentile``'s "linear"
interpolation and ``np.median``'s mean of the middle two, from each row sorted contiguously instead of numpy's strided
partition across the rows (docs/realsky.md, "Time"). The background's boxes (:mod:`hostlink.images.background`), the
stamps' ring medians and the median of the input frames (:mod:`hostlink.images.centroid`) take theirs here; tests:
tests/test_images_order_statistics.py."""

from __future__ import annotations

import numpy as np


def row_percentiles(rows: np.ndarray, percents: tuple[float, ...], counts: np.ndarray | None = None) -> np.ndarray:
    """``np.percentile(rows, percents, axis=1).T`` (method "linear") as float64, the same numbers, from each row
    sorted: numpy partitions along the first axis of the transposed rows, a strided pass per order statistic, many
    times slower than sorting each contiguous row (docs/realsky.md, "Time"). The interpolation is
    numpy's own: v = (n - 1) q / 100 between the neighbouring order statistics a, b with gamma = v - floor(v):
    a + (b - a) gamma, or b - (b - a)(1 - gamma) when gamma >= 0.5. ``counts``: each row's number of finite values,
    the rest NaN (sorted last), for ``np.percentile`` of each row's finite values (in one call, not one per row)."""
    return sorted_row_percentiles(np.sort(rows, axis=1), percents, counts)


def sorted_row_percentiles(
    ordered: np.ndarray, percents: tuple[float, ...], counts: np.ndarray | None = None
) -> np.ndarray:
    """:func:`row_percentiles` of rows already sorted (``ordered``)."""
    n = np.full((ordered.shape[0], 1), ordered.shape[1]) if counts is None else np.asarray(counts)[:, None]
    below, above, gamma = _percentile_ranks(n, percents)
    a = np.take_along_axis(ordered, below, axis=1)
    b = np.take_along_axis(ordered, above, axis=1)
    return _interpolated_percentiles(a, b, gamma)


def _percentile_ranks(n: np.ndarray, percents: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """numpy's "linear" percentile of ``n`` (rows, 1) values at ``percents``: the ranks (from 0) of the two
    neighbouring order statistics and the weight of the second, (rows, len(percents)) each (v = (n - 1) q / 100,
    gamma = v - floor(v))."""
    virtual = (n - 1) * (np.asarray(percents, dtype=np.float64) / 100.0)
    below = np.floor(virtual)
    gamma = virtual - below
    return np.minimum(below, n - 1).astype(np.intp), np.minimum(below + 1, n - 1).astype(np.intp), gamma


def _interpolated_percentiles(a: np.ndarray, b: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """numpy's interpolation between neighbouring order statistics ``a``, ``b`` with weight ``gamma``:
    a + (b - a) gamma, or b - (b - a)(1 - gamma) when gamma >= 0.5, as float64."""
    diff = b - a
    out = a + diff * gamma
    upper = np.broadcast_to(gamma >= 0.5, out.shape)
    out[upper] = (b - diff * (1 - gamma))[upper]
    return out.astype(np.float64)


def sorted_medians(ordered: np.ndarray, axis: int) -> np.ndarray:
    """``np.median(values, axis=axis)`` of values already sorted along ``axis`` (``ordered``), the same numbers for
    any dtype: the middle value, or the mean of the middle two, each taken by ``np.mean`` as ``np.median`` takes it
    (in the values' own float type; float64 for integers, whose sum would wrap in theirs). ``np.median``'s rule, where
    :func:`sorted_row_percentiles` at 50 % is ``np.percentile``'s interpolation (which can differ in the last
    bit)."""
    n = ordered.shape[axis]
    return np.mean(np.take(ordered, [n // 2] if n % 2 else [n // 2 - 1, n // 2], axis=axis), axis=axis)


def row_medians(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The median of each row of ``values`` (n, p) over its ``valid`` entries (NaN where none): the rows wholly
    valid (every stamp inside the image) at once, each sorted (:func:`sorted_medians`: ``np.median``'s numbers, which
    it finds by a slower strided partition across the rows), the others one by one (``np.nanmedian``'s masked arrays
    are slower still)."""
    out = np.full(values.shape[0], np.nan)
    whole = valid.all(axis=1)
    if whole.any():
        out[whole] = sorted_medians(np.sort(values[whole], axis=1), axis=1)
    for k in np.flatnonzero(~whole & valid.any(axis=1)):
        out[k] = np.median(values[k][valid[k]])
    return out
