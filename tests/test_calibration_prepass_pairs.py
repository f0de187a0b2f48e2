"""Large frames (docs/realsky.md "Large frames"): the calibration pre-pass (scale and parity) forms at most
``PREPASS_MAX_PAIRS`` star pairs, whatever the frames' star counts (its pair table grows as n^2 per frame and is held
for all its frames at once), and a session under that budget is untouched."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from synthetic_sessions import synthetic_session

from hostlink.calibration import robust
from hostlink.calibration.robust import prepass_rows, scale_and_parity_of_sample
from hostlink.sky.simulate import seed004_camera
from onboard.params import Distortion

TRUTH = seed004_camera()


def _pairs(counts) -> int:
    counts = np.asarray(counts, dtype=np.int64)
    return int(np.sum(counts * (counts - 1) // 2))


def test_prepass_rows_none_under_the_budget():
    starts = np.concatenate([[0], np.cumsum([30, 200, 45])])
    assert prepass_rows(starts, _pairs([30, 200, 45])) is None


def test_prepass_rows_the_largest_even_cap_that_fits():
    counts = np.array([30, 1000, 400, 5, 2500])
    starts = np.concatenate([[0], np.cumsum(counts)])
    budget = 200_000
    keep = prepass_rows(starts, budget)
    kept = np.array([np.count_nonzero(keep[a:b]) for a, b in zip(starts[:-1], starts[1:], strict=True)])
    cap = kept.max()
    assert _pairs(kept) <= budget < _pairs(np.minimum(counts, cap + 1))  # the largest cap that fits
    assert np.all(kept == np.minimum(counts, cap))  # every frame the same cap, small frames whole
    for a, b, n in zip(starts[:-1], starts[1:], counts, strict=True):
        rows = np.flatnonzero(keep[a:b])
        assert rows[0] == 0 and rows[-1] == n - 1  # spread over the frame's rows, its first and last kept
        if n > cap:
            assert np.ptp(np.diff(rows)) <= 1  # evenly spaced (rounded)


def test_prepass_thinned_gives_the_scale_and_parity(monkeypatch):
    """A nominal 3 % long and no distortion known: the thinned pre-pass (a tenth of the pairs) finds the scale
    within 1e-3 of the full one (the vote's tolerance is 3 %, which the fit then refines; the full one settles it to
    ~1e-5: robust.PREPASS_MAX_FRAMES) and the same normal parity, and forms no more pairs than its budget."""
    truth = TRUTH
    s = synthetic_session(truth, 60, stars_per_frame=(40, 80), noise_px=0.05, misidentified_fraction=0.03, seed=7)
    nominal = truth.with_focal_length_mm(truth.focal_length_mm * 1.03)
    nominal = replace(nominal, distortion=Distortion())
    theta = nominal.model_vector(np.float64)
    full = scale_and_parity_of_sample(s.data, theta)
    budget = _pairs(np.diff(s.data.frame_starts)) // 10
    formed = []
    original = robust.pair_table

    def counting(data, chunk_obs=robust.PAIR_BLOCK_OBS):
        table = original(data, chunk_obs)
        formed.append(sum(int(c.pairs_per_frame.sum()) for c in table))
        return table

    monkeypatch.setattr(robust, "pair_table", counting)
    monkeypatch.setattr(robust, "PREPASS_MAX_PAIRS", budget)
    thinned = scale_and_parity_of_sample(s.data, theta)
    assert formed and formed[0] <= budget
    assert thinned.scale == pytest.approx(full.scale, abs=1e-3)
    assert full.scale == pytest.approx(1 / 1.03, abs=2e-3)  # the nominal's 3 % (distortion left: ~1e-3)
    assert not thinned.mirrored and not full.mirrored
