"""The guided admission's pair search (hostlink.images.guided._admissions) against the full candidate x prediction
matrices it replaced: the same admissions, row for row and star for star, on random frames crowded enough that
candidates have several predictions within reach, ties of distance, rivals and shared matches included."""

import numpy as np
import pytest

from hostlink.images.blends import could_be
from hostlink.images.guided import CONTAINMENT_SIGMAS, UNRESOLVED_PX, _admissions


def _dense(rows, cand, predictions, sigma_pred, window):
    """The admission over full (candidates x predictions) matrices and an argmin over every row (the former code; a
    row's sigma without its elongated blend's bound where the prediction is a blend's reference)."""
    x, y, mag, sigma_px, own_px = rows
    xp, yp, predicted_mag, sigma_ref = predictions
    row_px = np.where(sigma_ref[None, :] > 0, own_px[cand, None], sigma_px[cand, None])
    radius = CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + row_px**2 + sigma_ref[None, :] ** 2)
    d2 = (x[cand, None] - xp[None, :]) ** 2 + (y[cand, None] - yp[None, :]) ** 2
    agree = np.abs(mag[cand, None] - predicted_mag[None, :]) <= window
    rivals = (d2 <= np.maximum(radius, UNRESOLVED_PX) ** 2) & could_be(predicted_mag[None, :], mag[cand, None], window)
    match = (d2 <= radius**2) & agree
    nearest_row = np.argmin((x[:, None] - xp[None, :]) ** 2 + (y[:, None] - yp[None, :]) ** 2, axis=0)
    out_rows, out_stars = [], []
    for i in np.flatnonzero(np.count_nonzero(match, axis=1) == 1):
        j = int(np.flatnonzero(match[i])[0])
        if np.count_nonzero(rivals[i]) != 1 or np.count_nonzero(match[:, j]) != 1 or nearest_row[j] != cand[i]:
            continue
        out_rows.append(cand[i])
        out_stars.append(j)
    return np.array(out_rows, dtype=np.int64), np.array(out_stars, dtype=np.int64)


@pytest.mark.parametrize("seed", range(12))
def test_pair_search_admits_what_the_full_matrices_admit(seed):
    rng = np.random.default_rng(seed)
    n_rows, n_stars = int(rng.integers(50, 400)), int(rng.integers(30, 300))
    size = 60.0 + 200.0 * rng.random()  # a small field: several predictions within reach of a row
    x, y = size * rng.random(n_rows), size * rng.random(n_rows)
    # a few rows on a quarter-pixel grid: exact ties of distance to a prediction on the same grid
    x[::7], y[::7] = np.round(4 * x[::7]) / 4, np.round(4 * y[::7]) / 4
    mag = rng.uniform(-4.0, 0.0, n_rows)
    sigma_px = rng.uniform(0.05, 1.5, n_rows)
    # some rows are elongated blends: their sigma without the bound is smaller
    own_px = np.where(rng.random(n_rows) < 0.3, sigma_px * rng.uniform(0.2, 1.0, n_rows), sigma_px)
    xp, yp = size * rng.random(n_stars), size * rng.random(n_stars)
    xp[::5], yp[::5] = np.round(4 * xp[::5]) / 4, np.round(4 * yp[::5]) / 4
    # some predictions placed on rows (admissions), some near them
    k = min(n_rows, n_stars) // 2
    xp[:k], yp[:k] = x[:k] + rng.normal(0.0, 0.3, k), y[:k] + rng.normal(0.0, 0.3, k)
    predicted_mag = np.concatenate([mag[:k] + rng.normal(0.0, 0.2, k), rng.uniform(-4.0, 0.0, n_stars - k)])
    sigma_ref = np.where(rng.random(n_stars) < 0.2, rng.uniform(0.0, 2.0, n_stars), 0.0)
    cand = np.flatnonzero(rng.random(n_rows) < 0.7)
    args = ((x, y, mag, sigma_px, own_px), cand, (xp, yp, predicted_mag, sigma_ref), 0.2, 0.5)
    rows, stars = _admissions(*args)
    want_rows, want_stars = _dense(*args)
    assert want_rows.size > 0  # the case exercises admissions
    order = np.argsort(rows)
    np.testing.assert_array_equal(rows[order], want_rows)
    np.testing.assert_array_equal(stars[order], want_stars)


def test_no_candidate_or_no_prediction_admits_nothing():
    x = np.array([1.0, 2.0])
    rows = (x, x, np.zeros(2), np.ones(2), np.ones(2))
    predictions = (x, x, np.zeros(2), np.zeros(2))
    for cand, pred in ((np.zeros(0, np.int64), predictions), (np.arange(2), tuple(p[:0] for p in predictions))):
        got_rows, got_stars = _admissions(rows, cand, pred, 0.2, 0.5)
        assert got_rows.size == 0 and got_stars.size == 0
