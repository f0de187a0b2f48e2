"""The own matcher's operation budget (hostlink.images.identify.MAX_ANCHOR_PAIRS, _anchor_schedule): a frame it
cannot identify stops after a fixed number of anchor pairs, not after minutes; the order the pairs are tried in keeps,
within the budget, every pair at the nominal scale and the pairs of the brightest stars at every other scanned
focal-length scale, and the budget cuts nothing of the rounds at a known scale."""

import numpy as np

from hostlink.images.identify import (
    ANCHOR_STARS,
    DEEP_ANCHOR_STARS,
    DEEP_MATCH_STARS,
    MATCH_STARS,
    MAX_ANCHOR_PAIRS,
    SCAN_SCALES,
    _anchor_schedule,
)


def _tries(schedule):
    return [(scale, pair) for scale, pairs in schedule for pair in pairs]


def test_at_a_known_scale_the_pairs_are_tried_brightest_first_and_the_deep_round_adds_only_new_ones():
    first = _tries(_anchor_schedule(MATCH_STARS, ANCHOR_STARS, 0, (1.0,)))
    deep = _tries(_anchor_schedule(DEEP_MATCH_STARS, DEEP_ANCHOR_STARS, ANCHOR_STARS, (1.0,)))
    assert [p for _, p in first] == [(i, j) for i in range(ANCHOR_STARS) for j in range(i + 1, ANCHOR_STARS)]
    assert not {p for _, p in first} & {p for _, p in deep}
    assert {p for _, p in first} | {p for _, p in deep} == {
        (i, j) for i in range(DEEP_ANCHOR_STARS) for j in range(i + 1, DEEP_ANCHOR_STARS)
    }
    # both rounds at a known scale fit the budget: it cuts only scans
    assert len(first) + len(deep) <= MAX_ANCHOR_PAIRS


def test_over_a_scan_the_budget_keeps_the_nominal_and_the_three_brightest_stars_pairs_at_every_scale():
    tries = _tries(_anchor_schedule(MATCH_STARS, ANCHOR_STARS, 0, SCAN_SCALES))
    anchor_pairs = [(i, j) for i in range(ANCHOR_STARS) for j in range(i + 1, ANCHOR_STARS)]
    # every pair among the anchor stars at every scale, each once
    every = {(s, p) for s in SCAN_SCALES for p in anchor_pairs}
    assert len(tries) == len(every) and set(tries) == every
    # first every pair at the nominal scale, in the order of a known scale
    assert tries[: len(anchor_pairs)] == [(SCAN_SCALES[0], p) for p in anchor_pairs]
    # within the budget, beyond that: the three pairs among the three brightest at every other scale (one false star
    # among them still leaves a pair of true stars, at the farthest scale too)
    kept = set(tries[:MAX_ANCHOR_PAIRS])
    assert {(s, p) for s in SCAN_SCALES[1:] for p in ((0, 1), (0, 2), (1, 2))} <= kept
    # ... tried star by star: no pair of a fainter star before those of a brighter one
    faintest = [max(p) for _, p in tries[len(anchor_pairs) :]]
    first_block = 3 * (len(SCAN_SCALES) - 1)
    assert max(faintest[:first_block]) == 2 and np.all(np.diff(faintest[first_block:]) >= 0)


def test_a_frame_with_fewer_stars_than_anchors_gets_only_its_pairs():
    tries = _tries(_anchor_schedule(4, ANCHOR_STARS, 0, SCAN_SCALES[:2]))
    assert sorted({p for _, p in tries}) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
