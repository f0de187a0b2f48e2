"""A session's optional columns (docs/file-formats.md: ``sigma_px``, ``blend_px``, ``saturated``, ``snr``, ...), kept
as text in :attr:`Session.extra`: read as numbers or flags in one place, and the pixel uncertainties written as text
in one place."""

from __future__ import annotations

import math

import numpy as np

from hostlink.files.session.data import Session


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
