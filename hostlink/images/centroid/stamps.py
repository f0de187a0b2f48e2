"""The stamps of pixels around stars, processed in blocks of bounded memory (:mod:`hostlink.images.centroid`)."""

from __future__ import annotations

import numpy as np


def _in_chunks(half_px: int, n: int, block):
    """``block(slice)`` over consecutive slices of the n stars, each of at most the package's ``_STAMP_BUDGET_PX``
    pixels of stamps of half-width ``half_px``; the results (an array or a tuple of arrays per slice)
    concatenated."""
    from hostlink.images import centroid  # the budget is the package's setting (a test bounds it)

    size = max(1, centroid._STAMP_BUDGET_PX // (2 * half_px + 2) ** 2)
    if n <= size:
        return block(slice(0, n))
    parts = [block(slice(k, min(k + size, n))) for k in range(0, n, size)]
    if isinstance(parts[0], tuple):
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))
    return np.concatenate(parts)


def _stamps(image: np.ndarray, x: np.ndarray, y: np.ndarray, half: int):
    """The (2 half + 1)^2 pixels around each star's nearest pixel: (cols (N, W), rows (N, H) as float pixel
    coordinates, the pixel values (N, H, W) (0 outside the image) and a mask (N, H, W), True inside the image). The
    pixels are taken by their flat indices (one ``take``, faster than indexing by rows and columns: docs/realsky.md,
    "Time"), and zeroed outside the image only when a stamp reaches beyond it."""
    h, w = image.shape
    offsets = np.arange(-half, half + 1)
    cols = np.rint(x).astype(np.int64)[:, None] + offsets[None, :]
    rows = np.rint(y).astype(np.int64)[:, None] + offsets[None, :]
    in_rows, in_cols = (rows >= 0) & (rows < h), (cols >= 0) & (cols < w)
    inside = in_rows[:, :, None] & in_cols[:, None, :]
    flat = (np.clip(rows, 0, h - 1) * w)[:, :, None] + np.clip(cols, 0, w - 1)[:, None, :]
    values = np.take(image, flat)
    if not (in_rows.all() and in_cols.all()):
        values = np.where(inside, values, 0.0)
    return cols.astype(np.float64), rows.astype(np.float64), values, inside
