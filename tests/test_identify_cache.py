"""What the rounds of hostlink.images.identify.identify_iteratively share (PairCache) gives the same answers as
building everything again: the own matcher's pair table cut from a wider and deeper one, or from the cut held when
asked again as deep over no wider an angle, is the table a fresh build gives (pair for pair, in the same order),
pairs of exactly equal angle are ordered by their stars, and the guided admission reuses the rounds' last
calibration only where it is the calibration it would run."""

import math

import numpy as np
import pytest

from hostlink.images.identify import PairCache, _sky, _ties_by_stars, pair_catalogue
from hostlink.images.pairtable import ANGLE_SAMPLE_PAIRS
from hostlink.images.skyindex import pair_arrays
from hostlink.sky.catalogue import load_catalogue

#: A 10-deg table to Hp 6.5: ~10^5 pairs, built in well under a second.
ANGLE_RAD = math.radians(10.0)
DEPTH_MAG = 6.5


@pytest.fixture(scope="module")
def sky():
    return _sky(load_catalogue())


def _assert_same_table(got, want):
    # pairs within rounding of the edge angle may fall either side of it (chord test against arccos): no window of
    # the matcher reaches them (hostlink.images.identify._pairs_of_angle stops 1e-9 rad short of the edge)
    got_a, got_b, got_angle = pair_arrays(got)  # every angle, computed from the pairs' stars
    want_a, want_b, want_angle = pair_arrays(want)
    inner = want_angle < want.max_angle_rad - 1e-12
    n = int(np.count_nonzero(inner))
    assert got.max_angle_rad == want.max_angle_rad
    np.testing.assert_array_equal(got_a[:n], want_a[:n])
    np.testing.assert_array_equal(got_b[:n], want_b[:n])
    np.testing.assert_array_equal(got_angle[:n], want_angle[:n])
    assert abs(got_a.size - want_a.size) <= 1
    m = n // ANGLE_SAMPLE_PAIRS  # the table keeps every 64th pair's angle, the searches' brackets
    np.testing.assert_array_equal(got.angle_sample_rad[:m], want.angle_sample_rad[:m])
    np.testing.assert_array_equal(want.angle_sample_rad[:m], want_angle[: m * ANGLE_SAMPLE_PAIRS : ANGLE_SAMPLE_PAIRS])
    np.testing.assert_array_equal(got.rows, want.rows)
    np.testing.assert_array_equal(got.tree.data, want.tree.data)
    if want.rank16 is None:
        assert got.rank16 is None
    else:
        np.testing.assert_array_equal(got.rank16, want.rank16)


@pytest.mark.parametrize(("angle_factor", "depth_delta"), [(1.0, 0.0), (0.97, 0.0), (1.0, -0.4), (0.95, -0.3)], ids=str)
def test_a_table_cut_from_the_cached_one_is_the_fresh_table(sky, angle_factor, depth_delta):
    cache = PairCache()
    first = cache.pairs(sky, ANGLE_RAD, DEPTH_MAG)  # built wider than asked, cut to it
    _assert_same_table(first, pair_catalogue(sky, ANGLE_RAD, DEPTH_MAG))
    held = cache._table
    angle, depth = ANGLE_RAD * angle_factor, DEPTH_MAG + depth_delta
    _assert_same_table(cache.pairs(sky, angle, depth), pair_catalogue(sky, angle, depth))
    assert cache._table is held  # cut, not built again


def test_a_wider_or_deeper_request_builds_the_table_again(sky):
    cache = PairCache()
    cache.pairs(sky, ANGLE_RAD, DEPTH_MAG)
    held = cache._table
    got = cache.pairs(sky, ANGLE_RAD, DEPTH_MAG + 0.3)
    assert cache._table is not held
    _assert_same_table(got, pair_catalogue(sky, ANGLE_RAD, DEPTH_MAG + 0.3))


def test_a_slightly_deeper_request_is_cut_from_the_held_table(sky):
    # the next round asks as deep as its identified stars go: 0.004 mag deeper on openstartracker's round 2
    from hostlink.images.skyindex import PAIR_CACHE_MAG_MARGIN

    cache = PairCache()
    cache.pairs(sky, ANGLE_RAD, DEPTH_MAG)
    held = cache._table
    depth = DEPTH_MAG + 0.8 * PAIR_CACHE_MAG_MARGIN
    got = cache.pairs(sky, ANGLE_RAD, depth)
    assert cache._table is held
    _assert_same_table(got, pair_catalogue(sky, ANGLE_RAD, depth))


@pytest.mark.parametrize("depth_delta", [0.0, -0.4], ids=["first-depth", "shallower"])
def test_a_narrower_request_at_the_same_depth_is_the_held_cuts_leading_part(sky, depth_delta):
    # a later round asks as deep over a hair narrower an angle (its calibrated focal length is a little longer)
    cache = PairCache()
    depth = DEPTH_MAG + depth_delta
    wide = cache.pairs(sky, ANGLE_RAD, depth)
    narrow = cache.pairs(sky, ANGLE_RAD * 0.999, depth)
    assert narrow.tree is wide.tree  # not cut again from the table
    _assert_same_table(narrow, pair_catalogue(sky, ANGLE_RAD * 0.999, depth))
    _assert_same_table(cache.pairs(sky, ANGLE_RAD, depth), wide)  # the held cut kept, not the narrower one


def test_pairs_of_equal_angle_are_ordered_by_their_stars():
    angle = np.array([0.3, 0.1, 0.2, 0.1, 0.2, 0.1])
    a = np.array([0, 7, 5, 2, 1, 2])
    b = np.array([1, 9, 6, 8, 3, 4])
    order = _ties_by_stars(np.argsort(angle, kind="stable"), angle, a, b)
    assert [(int(a[i]), int(b[i])) for i in order] == [(2, 4), (2, 8), (7, 9), (1, 3), (5, 6), (0, 1)]


def test_the_catalogue_and_database_are_read_once_per_catalogue():
    catalogue = load_catalogue()
    cache = PairCache()
    assert cache.sky(catalogue) is cache.sky(catalogue)
    bright = cache.bright(catalogue, 5.0)
    assert bright is cache.bright(catalogue, 5.0)
    assert np.all(bright.mag <= 5.0)
    assert len(bright) == int(np.count_nonzero(catalogue.mag <= 5.0))


def test_the_rounds_last_calibration_is_the_one_the_admission_would_run(monkeypatch):
    """identify_iteratively hands on the calibration of its final session from its final camera (the round after it
    added nothing); calibrating that session again from that camera gives the same camera, and the guided admission
    then runs no calibration of its own."""
    from dataclasses import replace

    from hostlink.calibration.run import calibrate_session
    from hostlink.images import guided
    from hostlink.images.identify import identify_iteratively
    from hostlink.sky.simulate import SimConfig, seed004_camera, simulate
    from onboard.params import Distortion

    camera = replace(seed004_camera(), distortion=Distortion(k1=-2e-9))
    sim = simulate(SimConfig(camera=camera, frames=4, noise_px=0.1, min_stars=8, max_stars=60, maglim=6.5, seed=7))
    blind = replace(sim.session, star_id=np.zeros_like(sim.session.star_id), ra_deg=None, dec_deg=None)
    nominal = replace(camera, distortion=Distortion(), focal_length_mm=camera.focal_length_mm * 1.03)
    result = identify_iteratively(blind, nominal, maglim=7.5)
    assert result.n_frames_identified == 4
    assert result.calibration is not None  # the last round added nothing: its calibration was run and kept
    again, _ = calibrate_session(result.session, result.camera, keep_failed=True)
    np.testing.assert_array_equal(
        again.params.model_vector(np.float64), result.calibration.params.model_vector(np.float64)
    )

    def no_second_calibration(*args, **kwargs):
        raise AssertionError("calibrated again")

    monkeypatch.setattr("hostlink.calibration.run.calibrate_session", no_second_calibration)
    got = guided._calibrated(result.session, result.camera, result.calibration)
    np.testing.assert_array_equal(got.model_vector(np.float64), again.params.model_vector(np.float64))


def _one_piece_table(sky, max_angle_rad, maglim):
    """The table as one ``query_pairs`` over all the stars and one sort by (angle, a, b): the build before it was
    staged in blocks (docs/realsky.md, "Speed"), the angle the same arccos of the same sums."""
    from scipy.spatial import cKDTree

    rows = np.flatnonzero(sky.mag <= maglim)
    found = cKDTree(sky.r[rows]).query_pairs(2.0 * math.sin(0.5 * max_angle_rad), output_type="ndarray")
    a, b = rows[found[:, 0]], rows[found[:, 1]]
    x, y, z = (np.ascontiguousarray(sky.r[:, axis]) for axis in range(3))
    angle = np.arccos(np.clip(x[a] * x[b] + y[a] * y[b] + z[a] * z[b], -1.0, 1.0))
    order = np.lexsort((b, a, angle))
    return a[order], b[order], angle[order]


@pytest.mark.parametrize(("groups", "block_pairs"), [(7, 1000), (32, 1 << 20)], ids=["small-blocks", "default"])
def test_the_staged_build_is_the_one_piece_table(sky, monkeypatch, groups, block_pairs):
    # many blocks, star groups and angle buckets: each pair found once, every pair in its place, bit for bit
    from hostlink.images import pairtable

    monkeypatch.setattr(pairtable, "PAIR_BUILD_STAR_GROUPS", groups)
    monkeypatch.setattr(pairtable, "PAIR_BUILD_BLOCK_PAIRS", block_pairs)
    got = pair_catalogue(sky, ANGLE_RAD, DEPTH_MAG)
    want_a, want_b, want_angle = _one_piece_table(sky, ANGLE_RAD, DEPTH_MAG)
    assert got.a.dtype == got.b.dtype == np.int32  # 8 bytes a pair, and the sampled angles
    assert got.a.size > 50 * 1000
    np.testing.assert_array_equal(got.a, want_a)
    np.testing.assert_array_equal(got.b, want_b)
    np.testing.assert_array_equal(got.angle_sample_rad, want_angle[:: pairtable.ANGLE_SAMPLE_PAIRS])
    np.testing.assert_array_equal(pair_arrays(got)[2], want_angle)


def test_a_search_among_the_sampled_angles_is_a_search_among_all_of_them(sky):
    # every pair's angle as a bound, either side, and values between and beyond them: the index np.searchsorted gives
    from hostlink.images.pairtable import angle_index

    table = pair_catalogue(sky, ANGLE_RAD, DEPTH_MAG - 1.0)
    _, _, angle = pair_arrays(table)
    bounds = np.concatenate([angle, np.nextafter(angle, 0.0), np.nextafter(angle, 1.0), [-1.0, 0.0, ANGLE_RAD, 1.0]])
    for side in ("left", "right"):
        want = np.searchsorted(angle, bounds, side=side)
        got = [angle_index(table.angle_sample_rad, table.columns, table.a, table.b, x, side) for x in bounds]
        np.testing.assert_array_equal(got, want)


def test_the_matchers_windows_of_a_cut_are_those_of_the_fresh_table(sky):
    # a window's bounds found among the cut's sampled angles, the angles between two samples computed again
    from hostlink.images.skyindex import pair_window

    cache = PairCache()
    cache.pairs(sky, ANGLE_RAD, DEPTH_MAG)
    cut = cache.pairs(sky, ANGLE_RAD * 0.9, DEPTH_MAG - 0.5)
    fresh_a, fresh_b, fresh_angle = pair_arrays(pair_catalogue(sky, ANGLE_RAD * 0.9, DEPTH_MAG - 0.5))
    for lo_rad in np.linspace(0.01, 0.8, 9) * ANGLE_RAD:
        lo, hi = np.searchsorted(fresh_angle, [lo_rad, lo_rad + 0.003])
        got_a, got_b = pair_window(cut, lo_rad, lo_rad + 0.003)
        assert got_a.size == hi - lo > 0
        np.testing.assert_array_equal(got_a, fresh_a[lo:hi])
        np.testing.assert_array_equal(got_b, fresh_b[lo:hi])
