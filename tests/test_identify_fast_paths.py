"""Identification's faster paths (issue 30) give exactly what the computations they replace gave: the verification's
one pair table (scale, vote, triples) against the functions that each build their own, the field's widest pair
without every pair's angle, and the extension's nearest neighbours and ambiguity from the pairs within reach
(extend._near_pairs) against the full (centroids x predicted stars) table of squared distances. Exact equality
throughout: the same Gram entries, the same squared distances and the same tests, so any difference is a bug, not
rounding."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.calibration import robust
from hostlink.calibration.data import build_data
from hostlink.images import blends, extend
from hostlink.images.skyindex import _Sky
from hostlink.images.verify import _Verified
from onboard.camera import pixels_to_unit


def _frame(seed: int, n: int, wrong: int, frames: int = 1):
    """``frames`` frames of ``n`` stars of a 10-deg field: catalogue directions r and measured directions b (a
    rotation of r, centroid noise), ``wrong`` of each frame's r replaced by random stars (misidentifications)."""
    rng = np.random.default_rng(seed)
    xs, ys, rs, keys = [], [], [], []
    theta = np.array([2000.0, 640.0, 480.0] + [0.0] * 7)
    for f in range(frames):
        x = rng.uniform(0.0, 1280.0, n)
        y = rng.uniform(0.0, 960.0, n)
        b = pixels_to_unit(x + rng.normal(0, 0.3, n), y + rng.normal(0, 0.3, n), theta)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        r = b @ q  # b = r q^T: a rotation (or a mirror: the triples' test is the point then)
        bad = rng.choice(n, wrong, replace=False)
        v = rng.normal(size=(wrong, 3))
        r[bad] = r[bad] + 0.05 * v / np.linalg.norm(v, axis=1, keepdims=True)
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        xs.append(x), ys.append(y), rs.append(r), keys.append(np.full(n, f))
    data = build_data(np.concatenate(xs), np.concatenate(ys), np.concatenate(rs), np.concatenate(keys))
    return data, theta


@pytest.mark.parametrize(("seed", "n", "wrong"), [(0, 12, 2), (1, 60, 15), (2, 300, 40)])
def test_one_pair_table_gives_what_each_function_gives(seed, n, wrong):
    data, theta = _frame(seed, n, wrong)
    table = robust.pair_table(data)
    assert robust.estimate_scale_of_table(data, table, theta) == robust.estimate_scale(data, theta)
    b = pixels_to_unit(data.x_px, data.y_px, theta)
    for min_agreement in (0.5, 0.7):
        expected = robust.vote_consistent_stars(data, b, rel_tol=0.005, abs_tol_rad=1.5e-3, min_agreement=min_agreement)
        got = robust.vote_of_table(table, b, data.n_obs, 0.005, 1.5e-3, min_agreement)
        assert np.array_equal(got, expected)
    keep = robust.vote_consistent_stars(data, b)
    assert robust.triple_handedness_of_table(table, b, keep) == robust.triple_handedness(data, b, keep)


@pytest.mark.parametrize("frames", [1, 5])
def test_widest_pair_without_every_angle(frames):
    data, _ = _frame(3, 40, 0, frames)
    # a frame of one star too: its own direction's rounding, as the pair table's minimum always counted it
    one = build_data(
        np.r_[data.x_px, 5.0],
        np.r_[data.y_px, 5.0],
        np.r_[data.r, [[0.0, 0.6, 0.8]]],
        np.r_[np.repeat(np.arange(frames), 40), frames],
    )
    for d in (data, one):
        for chunk_obs in (robust.PAIR_BLOCK_OBS, 50):
            chunks = robust.frame_chunks(d.frame_starts, chunk_obs)
            min_dot = min(robust._frame_pairs(d, f0, f1).min_dot_r for f0, f1 in chunks)
            expected = float(robust.angle_from_dot_rad(np.float64(min_dot)))  # every pair's table, as before
            assert robust.max_pair_angle_rad(d, chunk_obs=chunk_obs) == expected


def _extend_by_table(x_px, y_px, near, xp, yp, sky, radius, taken_rows, calibrated_mag, window):
    """The extension's matching as it was before the pairs within reach: the full (centroids, predicted) table."""
    d2 = (x_px[:, None] - xp[None, :]) ** 2 + (y_px[:, None] - yp[None, :]) ** 2
    free = np.flatnonzero(~taken_rows)
    own = d2[free]
    j = np.argmin(own, axis=1)
    nearest = own[np.arange(free.size), j]
    tied = own < 4.0 * nearest[:, None]
    tied[np.arange(free.size), j] = True
    ok = np.count_nonzero(tied, axis=1) == 1
    if calibrated_mag is not None:
        known = np.isfinite(calibrated_mag[free])
        able = tied & blends.could_be(sky.mag[near][None, :], calibrated_mag[free, None], window)
        single = known & (np.count_nonzero(able, axis=1) == 1)
        j = np.where(single, np.argmax(able, axis=1), j)
        ok |= single
    ok &= own[np.arange(free.size), j] <= radius * radius
    ok &= np.argmin(d2, axis=0)[j] == free
    return free[ok], near[j[ok]]


def _ambiguous_by_table(x_px, y_px, stars, near, xp, yp, sky, radius, detection_mag, window):
    d2 = (x_px[:, None] - xp[None, :]) ** 2 + (y_px[:, None] - yp[None, :]) ** 2
    other = (d2 <= radius * radius) & (near[None, :] != stars[:, None])
    bright_enough = sky.mag[near][None, :] <= sky.mag[stars][:, None] + extend.AMBIGUITY_MAG_MARGIN
    if detection_mag is not None:
        known = np.isfinite(detection_mag)
        explains = blends.could_be(sky.mag[near][None, :], detection_mag[:, None], window)
        bright_enough = np.where(known[:, None], explains, bright_enough)
    return np.any(other & bright_enough, axis=1)


@pytest.mark.parametrize("seed", range(6))
def test_extension_and_ambiguity_as_the_full_table(seed, monkeypatch):
    """Scenes with crowding (pairs closer than the radius), exact ties (a centroid equidistant from two predicted
    stars, two centroids equidistant from one) and unknown magnitudes: the same rows, stars and flags."""
    rng = np.random.default_rng(100 + seed)
    n_pred, n_cent = 400, 300
    xp = rng.uniform(0, 200, n_pred)
    yp = rng.uniform(0, 200, n_pred)
    xp[:20], yp[:20] = np.round(xp[:20]), np.round(yp[:20])
    pick = rng.choice(n_pred, n_cent, replace=False)
    x = xp[pick] + rng.normal(0, 1.0, n_cent)
    y = yp[pick] + rng.normal(0, 1.0, n_cent)
    x[:10], y[:10] = xp[:10] + 1.0, yp[:10]  # exactly 1 px right of a predicted star on the grid ...
    xp[20], yp[20] = xp[0] + 2.0, yp[0]  # ... with another 1 px on its other side: a tie
    x[10], y[10] = xp[1] - 1.0, yp[1]  # two centroids 1 px either side of predicted star 1
    near = np.arange(n_pred, dtype=np.int64) * 3
    sky = _Sky(np.arange(3 * n_pred), np.zeros((3 * n_pred, 3)), rng.uniform(2.0, 8.0, 3 * n_pred))
    taken = rng.random(n_cent) < 0.3
    mags = rng.uniform(2.0, 8.0, n_cent)
    mags[rng.random(n_cent) < 0.1] = np.nan
    radius = float(rng.choice([1.0, 1.5, 3.0]))
    v = _Verified(np.ones(1, bool), False, 1.0, 1.0, np.eye(3), np.zeros(1), np.ones(10))
    monkeypatch.setattr(extend, "_predict", lambda *a, **k: (near, xp, yp))
    monkeypatch.setattr(extend, "_match_radius_px", lambda *a, **k: radius)
    for calibrated in (None, mags):
        rows, stars = extend._extend(x, y, sky, np.ones(10), v, taken, 9.0, (200, 200), calibrated, 0.5)
        expected = _extend_by_table(x, y, near, xp, yp, sky, radius, taken, calibrated, 0.5)
        assert np.array_equal(rows, expected[0]) and np.array_equal(stars, expected[1])
        named = near[rng.choice(n_pred, n_cent)]
        flags = extend._ambiguous(x, y, named, sky, np.ones(10), v, (200, 200), 9.0, calibrated, 0.5)
        assert np.array_equal(flags, _ambiguous_by_table(x, y, named, near, xp, yp, sky, radius, calibrated, 0.5))


def _densest_by_every_start(values, width):
    """The densest window as it was counted before the blocks: every start's window by a binary search."""
    v = np.sort(values)
    upper = np.searchsorted(v, v + width, side="right")
    counts = upper - np.arange(v.size)
    i = int(np.argmax(counts))
    return float(np.median(v[i : upper[i]])), int(counts[i])


@pytest.mark.parametrize("seed", range(4))
def test_densest_window_as_every_start_counted(seed):
    """Log ratios as the scale sees them (a narrow mode among spread outliers), values rounded so that windows tie
    and values repeat, a uniform spread (every block a candidate), and sizes below and above the block bound's."""
    rng = np.random.default_rng(seed)
    for n in (3, 40, 300, 5000, 120_000):
        mode = np.concatenate([rng.normal(0.003, 0.002, n - n // 5), rng.uniform(-3.0, 1.0, n // 5)])
        for values in (mode, np.round(mode, 3), rng.uniform(-0.1, 0.1, n), np.round(rng.normal(0, 0.01, n), 2)):
            assert robust._densest_window(values, 0.02) == _densest_by_every_start(values, 0.02)


def _frames_of_random_counts(seed: int, frames: int, max_stars: int):
    """``frames`` frames of 1..``max_stars`` stars each (every count, frames of one star too), a quarter of each
    frame's catalogue directions misidentified, measured through a camera 2 % long (angles near the vote's
    tolerance, so both outcomes of the test occur): data and measured directions b."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, max_stars + 1, frames)
    xs, ys, rs, keys = [], [], [], []
    theta = np.array([2000.0, 640.0, 480.0] + [0.0] * 7)
    for f, n in enumerate(counts):
        x, y = rng.uniform(0.0, 1280.0, n), rng.uniform(0.0, 960.0, n)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        r = pixels_to_unit(x + rng.normal(0, 0.5, n), y + rng.normal(0, 0.5, n), theta) @ q
        bad = rng.random(n) < 0.25
        v = rng.normal(size=(int(bad.sum()), 3))
        r[bad] += 0.02 * v / np.linalg.norm(v, axis=1, keepdims=True)
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        xs.append(x), ys.append(y), rs.append(r), keys.append(np.full(n, f))
    data = build_data(np.concatenate(xs), np.concatenate(ys), np.concatenate(rs), np.concatenate(keys))
    b = pixels_to_unit(data.x_px, data.y_px, theta * np.r_[1.02, np.ones(9)])
    return data, b


@pytest.mark.parametrize("seed", range(6))
def test_the_vote_over_the_pair_table_is_the_vote_over_count_blocks_on_many_frames(seed):
    """The two layouts of the interstar vote (padded chunks in time order, :func:`robust.vote_of_table`; unpadded
    blocks of one star count, :func:`robust.vote_consistent_stars`) keep the same stars, over many frames of every
    count, chunks small enough to split the frames several ways, and thresholds from none to every other star."""
    data, b = _frames_of_random_counts(seed, frames=40, max_stars=30)
    mixed = 0  # the cases that keep some stars and drop others
    alone = np.repeat(np.diff(data.frame_starts) == 1, np.diff(data.frame_starts))
    for chunk_obs in (robust.PAIR_BLOCK_OBS, 97, 31):
        table = robust.pair_table(data, chunk_obs)
        for rel_tol, abs_tol_rad in ((0.03, 1e-3), (0.02, 2e-4), (0.005, 1.5e-3)):
            for min_agreement in (0.0, 0.3, 0.5, 0.7, 1.0):
                tolerances = {"rel_tol": rel_tol, "abs_tol_rad": abs_tol_rad, "min_agreement": min_agreement}
                expected = robust.vote_consistent_stars(data, b, chunk_obs=chunk_obs, **tolerances)
                got = robust.vote_of_table(table, b, data.n_obs, **tolerances)
                assert np.array_equal(got, expected), (chunk_obs, tolerances)
                mixed += 0 < np.count_nonzero(got) < data.n_obs
                assert not np.any(got[alone])  # a star alone in its frame agrees with no other, at any threshold
    assert mixed >= 27  # of 45 cases: both outcomes of the test occur, so the equality means something
