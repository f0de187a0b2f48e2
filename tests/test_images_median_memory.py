"""Large frames (docs/realsky.md "Large frames"): ``--median-of-inputs`` holds every frame once. Its median is taken
from the stack sorted in place, so it allocates no second stack (counted by tracemalloc, which numpy reports its
arrays to, not timed), with numpy's median."""

from __future__ import annotations

import tracemalloc

import numpy as np

from hostlink.images.centroid import session
from hostlink.images.centroid.session import _median_frame


def _peak_bytes(function, *args) -> tuple[object, int]:
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        out = function(*args)
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_median_frame_allocates_less_than_a_second_stack(monkeypatch):
    """12 frames of 300 x 400 float32 (5.8 MB): the median's own allocations are its float64 frame (0.96 MB), the
    two middle frames taken and the NaN test's strips (lowered here to 4 rows), below half the stack (a sorted copy
    would be the whole stack)."""
    monkeypatch.setattr(session, "_NAN_STRIP_ELEMENTS", 12 * 4 * 400)
    rng = np.random.default_rng(4)
    stack = np.round(rng.normal(size=(12, 300, 400)) * 8).astype(np.float32)
    expected = np.median(stack, axis=0).astype(np.float64)
    median, peak = _peak_bytes(_median_frame, stack)
    np.testing.assert_array_equal(median, expected)
    assert peak < 0.5 * stack.nbytes, (peak, stack.nbytes)


def test_median_frame_finds_a_nan_in_any_strip(monkeypatch):
    monkeypatch.setattr(session, "_NAN_STRIP_ELEMENTS", 5 * 2 * 7)
    stack = np.arange(5 * 9 * 7, dtype=np.float64).reshape(5, 9, 7)
    stack[3, 8, 6] = np.nan  # in the last strip only
    expected = np.median(stack, axis=0)
    out = _median_frame(stack.copy())
    np.testing.assert_array_equal(out, expected)
    assert np.isnan(out[8, 6]) and np.isfinite(out[:8]).all()
