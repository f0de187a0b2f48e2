"""The project's own lost-in-space matcher (:mod:`hostlink.images.identify`, module docstring step 1): pair-anchored
hypothesise-and-test over the catalogue pairs of the same angle (:func:`anchor_candidates`), the order and budget of its
anchor pairs (:func:`_anchor_schedule`, :data:`MAX_ANCHOR_PAIRS`) and the catalogue depth it indexes
(:func:`fallback_depth_mag`), and the tables it needs for a camera built beforehand (:func:`prepare_cache`)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hostlink.images import solver_adapter
from hostlink.images.skyindex import PairCache, PairCatalogue, _field_sr, check_field, pair_window
from hostlink.sky.catalogue import Catalogue
from onboard.params import CameraParams

#: Fallback matcher: the brightest centroids of a frame it uses; pairs among the first ANCHOR_STARS are anchors.
MATCH_STARS = 20


ANCHOR_STARS = 7


#: Fallback matcher, second round at a known scale for frames the first did not identify (faint fields where
#: noise outranks some stars): deeper, and slower (docs/realsky.md, "Figures behind the speed choices").
DEEP_MATCH_STARS = 40


DEEP_ANCHOR_STARS = 12


#: Fallback matcher: anchor-pair angle tolerance, relative (the focal length is known to ~0.1 % from the session's
#: identified frames; a scan step otherwise) plus :data:`ANCHOR_ABS_TOL_PX` of centroid error and distortion.
ANCHOR_REL_TOL = 0.002


ANCHOR_ABS_TOL_PX = 1.5


#: ... once the session's identified frames have measured the scale (they agree to +-0.05 % on the real set):
#: half the scan's tolerance, half the hypotheses.
ANCHOR_REL_TOL_KNOWN = 0.001


#: Fallback matcher: a star predicted by an anchor hypothesis must fall within this radius [px] of a catalogue star.
HIT_RADIUS_PX = 2.0


#: Fallback matcher: hits beyond the anchor pair a hypothesis needs (at a catalogue density of 1 star per square
#: degree and a 4 px = 1' radius on a 6 deg field, three chance hits on one of ~10^4 hypotheses have a probability of
#: ~1e-3; the verification then tests every star again).
MIN_HITS = 3


#: Fallback matcher: focal-length scales scanned when no identified frame gives one (a nominal within 10 %).
#: Ordered from the nominal outward (a good nominal is found first); the step is twice :data:`ANCHOR_REL_TOL`.
SCAN_SCALES = tuple(sorted((float(s) for s in np.round(np.arange(0.90, 1.1001, 0.004), 3)), key=lambda s: abs(s - 1)))


def _triad_frame(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the TRIAD frames (Black 1964) of the vector pairs: columns t1 = v1, t2 = v1 x v2 / |v1 x v2|,
    t3 = t1 x t2."""
    t2 = np.cross(v1, v2)
    t2 /= np.linalg.norm(t2, axis=-1, keepdims=True)
    return np.stack([v1, t2, np.cross(v1, t2)], axis=-1)


def _triad_inverse(b1, b2, r1, r2, r_frame: np.ndarray | None = None) -> np.ndarray:
    """C^T (M, 3, 3) of the TRIAD attitudes (Black 1964) mapping r1 -> b1 exactly and r2 toward b2: b = C r.
    ``r_frame``: :func:`_triad_frame` of (r1, r2) when already computed (it serves both parities of b)."""
    if r_frame is None:
        r_frame = _triad_frame(r1, r2)
    return r_frame @ np.swapaxes(_triad_frame(b1, b2), -1, -2)


@dataclass(frozen=True)
class _PairsOfAngle:
    """The catalogue pairs whose separation is within ``slack_rad`` of ``angle_rad`` [rad], as partner lists: the
    partners of sky star a are ``partner[offset[a]:offset[a + 1]]`` (both orders of every pair); ``member`` (S,)
    bool: the stars with a partner."""

    angle_rad: float
    slack_rad: float
    offset: np.ndarray
    partner: np.ndarray
    member: np.ndarray


def _pairs_of_angle(pairs: PairCatalogue, angle_rad: float, slack_rad: float) -> _PairsOfAngle | None:
    """The catalogue pairs of separation ``angle_rad`` +- ``slack_rad`` [rad] (:class:`_PairsOfAngle`); None when
    the window is not inside (0, max_angle_rad), where the pair index is not complete."""
    if angle_rad - slack_rad <= 0.0 or angle_rad + slack_rad + 1e-9 >= pairs.max_angle_rad:
        return None
    a, b = pair_window(pairs, angle_rad - slack_rad, angle_rad + slack_rad)
    star = np.concatenate([a, b])
    other = np.concatenate([b, a])
    count = np.bincount(star, minlength=pairs.r.shape[0])
    offset = np.concatenate([[0], np.cumsum(count)])
    key = star if pairs.rank16 is None else pairs.rank16[star]  # the same order: rows ascend with the sky index
    partner = other[np.argsort(key, kind="stable")]
    return _PairsOfAngle(angle_rad, slack_rad, offset, partner, count > 0)


def _pyramid_may_hit(
    columns: tuple[np.ndarray, np.ndarray, np.ndarray],
    first: np.ndarray,
    second: np.ndarray,
    with_first: _PairsOfAngle | None,
    with_second: _PairsOfAngle | None,
) -> np.ndarray:
    """(M,) bool: the anchor hypotheses (``first``, ``second``: sky indices of the anchor stars b_i, b_j;
    ``columns``: the columns of the sky's unit vectors, :func:`hostlink.images.skyindex.sky_columns`) that can put a
    third star b_m within the hit chord c of a catalogue star s at all: a necessary condition only (the k-d tree, or
    the distances to the stars :func:`_pyramid_candidates` finds, decide). A hypothesis (TRIAD) maps b_i onto its
    first star exactly, b_j onto the great circle toward its second star, off it by the pair's angle mismatch d (at
    most the anchor window's tolerance), and preserves angles. So s lies at the angle (b_i, b_m) from the first star
    to within the angle 2 asin(c / 2) < 1.001 c that the chord subtends, and at (b_j, b_m) from the second to within
    1.001 c + d: s is a partner of the first star in ``with_first`` and of the second in ``with_second``, the pairs
    of those angles with slacks of at least that. A side given as None is not tested."""
    return _pyramid_candidates(columns, first, second, with_first, with_second)[0]


def _columns_of(
    columns: tuple[np.ndarray, np.ndarray, np.ndarray], stars: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The columns x, y, z of the sky's unit vectors (``columns``) at ``stars``."""
    x, y, z = columns
    return x[stars], y[stars], z[stars]


def _pyramid_candidates(
    columns: tuple[np.ndarray, np.ndarray, np.ndarray],
    first: np.ndarray,
    second: np.ndarray,
    with_first: _PairsOfAngle | None,
    with_second: _PairsOfAngle | None,
    second_columns: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`_pyramid_may_hit` and the catalogue stars that pass it: (may, hypotheses, stars), every (hypothesis h,
    star s) that passed both angle tests; (may, None, None) when a side is None. Every catalogue star within the hit
    chord of h's prediction of b_m is among them (the necessary condition), so their distances alone decide whether
    h puts b_m on a star (:func:`_best_hypothesis`), without the k-d tree. ``second_columns``: the second stars'
    unit vectors as columns (:func:`_columns_of`), the same for every third star of an anchor pair."""
    may = np.ones(first.size, dtype=bool)
    for side, stars in ((with_first, first), (with_second, second)):  # each anchor star has such a partner
        if side is not None:
            may &= side.member[stars]
    if with_first is None or with_second is None:
        return may, None, None
    # ... and one and the same s: every partner s of the first star, at the second angle from the second star
    cand = np.flatnonzero(may)
    lo = with_first.offset[first[cand]]
    count = with_first.offset[first[cand] + 1] - lo
    # the partners' positions: lo of its hypothesis plus the rank within it (one repeat of the per-hypothesis shift)
    hyp = np.repeat(cand, count)
    s = with_first.partner[np.arange(hyp.size) + np.repeat(lo - (np.cumsum(count) - count), count)]
    # |angle - with_second.angle_rad| <= slack as cosines (arccos decreases on [0, pi]; the window starts above 0);
    # :func:`hostlink.images.skyindex._dot_rows`'s sum, the second stars' columns gathered once per anchor pair
    x, y, z = columns
    second_x, second_y, second_z = second_columns if second_columns is not None else _columns_of(columns, second)
    dot = second_x[hyp] * x[s] + second_y[hyp] * y[s] + second_z[hyp] * z[s]
    cos_hi = math.cos(with_second.angle_rad - with_second.slack_rad)
    cos_lo = math.cos(min(with_second.angle_rad + with_second.slack_rad, math.pi))
    ok = (dot >= cos_lo) & (dot <= cos_hi)
    hyp, s = hyp[ok], s[ok]
    may[:] = False
    may[hyp] = True
    return may, hyp, s


def anchor_candidates(
    b: np.ndarray,
    pairs: PairCatalogue,
    tree,
    tree_rows: np.ndarray,
    focal_px: float,
    anchor_stars: int = ANCHOR_STARS,
    rel_tol: float = ANCHOR_REL_TOL,
    skip_first: int = 0,
    anchor_pairs: list[tuple[int, int]] | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray, bool]]:
    """The project's own lost-in-space matcher (a pair-anchored hypothesise-and-test, as in the pyramid method of
    Mortari et al. 2004): for an anchor pair of bright measured directions ``b`` (K, 3), every catalogue pair of the
    same angle (within ``rel_tol`` x angle + :data:`ANCHOR_ABS_TOL_PX`), in both orders and both
    parities, gives an attitude (TRIAD) that predicts the other K - 2 stars; the hypothesis whose predictions land
    on catalogue stars (``tree``: a k-d tree of the catalogue unit vectors ``tree_rows``) within
    :data:`HIT_RADIUS_PX` most often, at least :data:`MIN_HITS` times, is proposed. Yields, anchor pair by anchor
    pair (brightest first, pairs among the first ``anchor_stars``), (rows into b, sky indices, mirrored); the
    caller verifies each until one holds. A hypothesis must first put a third anchor star on a catalogue star (the
    pyramid's pruning); only the hypotheses a necessary condition on the catalogue pairs leaves
    (:func:`_pyramid_may_hit`) are tried, which changes no answer and skips most of the work on a narrow field, and
    whether they put the third star on a catalogue star is decided by the distances to the few stars that condition
    found (:func:`_pyramid_candidates`) rather than by the tree.
    ``anchor_pairs``: only these anchor pairs (rows into b), in this order, instead of every pair among the first
    ``anchor_stars`` (:func:`_anchor_schedule`)."""
    k = b.shape[0]
    if k < 2 + MIN_HITS:
        return
    hit_chord = HIT_RADIUS_PX / focal_px
    # slacks of :func:`_pyramid_may_hit`: twice the hit chord from the first anchor star; from the second, plus the
    # largest anchor-window tolerance (its pair's angle mismatch is at most that)
    slack_first_rad = 2.0 * hit_chord
    slack_second_rad = slack_first_rad + rel_tol * pairs.max_angle_rad + ANCHOR_ABS_TOL_PX / focal_px
    windows: dict[tuple[int, int, float], _PairsOfAngle | None] = {}

    def pairs_of(p: int, q: int, slack_rad: float) -> _PairsOfAngle | None:
        """The catalogue pairs of the angle (b_p, b_q) +- ``slack_rad`` (:func:`_pyramid_may_hit`)."""
        key = (min(p, q), max(p, q), slack_rad)
        if key not in windows:
            angle_rad = float(np.arccos(np.clip(b[key[0]] @ b[key[1]], -1.0, 1.0)))
            windows[key] = _pairs_of_angle(pairs, angle_rad, slack_rad)
        return windows[key]

    if anchor_pairs is None:
        anchor_pairs = list(zip(*np.triu_indices(min(k, anchor_stars), 1), strict=True))
    for i, j in anchor_pairs:
        ang = float(np.arccos(np.clip(b[i] @ b[j], -1.0, 1.0)))
        if j < skip_first:
            continue  # an anchor pair a previous round already tried
        tol = rel_tol * ang + ANCHOR_ABS_TOL_PX / focal_px
        if ang + tol > pairs.max_angle_rad or ang < 20.0 * tol:
            continue  # short pairs leave the roll about them too loose for the predictions
        in_window_a, in_window_b = pair_window(pairs, ang - tol, ang + tol)
        if in_window_a.size == 0:
            continue
        first = np.concatenate([in_window_a, in_window_b])
        second = np.concatenate([in_window_b, in_window_a])
        thirds = [m for m in range(min(k, anchor_stars)) if m not in (i, j)]
        if not thirds:
            continue
        # pyramid pruning, first a necessary condition (the pair index's stars are the tree's): a hypothesis that
        # cannot put any third anchor star on a catalogue star is dropped before its attitude is computed
        may_hit = np.ones((len(thirds), first.size), dtype=bool)
        near: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(thirds)  # None: the tree decides
        if tree is pairs.tree:
            windows_of_thirds = [(pairs_of(i, m, slack_first_rad), pairs_of(j, m, slack_second_rad)) for m in thirds]
            first, second, may_hit, near = _pyramid_prefilter(pairs, first, second, windows_of_thirds)
            if first.size == 0:
                continue
        r_frame = _triad_frame(pairs.r[first], pairs.r[second])  # the catalogue's side, for both parities
        for mirrored in (False, True):
            found = _best_hypothesis(
                b, (i, j), first, second, thirds, may_hit, tree, tree_rows, hit_chord, pairs.r, mirrored, near, r_frame
            )
            if found is not None:
                yield found[0], found[1], mirrored


def _pyramid_prefilter(
    pairs: PairCatalogue,
    first: np.ndarray,
    second: np.ndarray,
    windows: list[tuple[_PairsOfAngle | None, _PairsOfAngle | None]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray] | None]]:
    """:func:`_pyramid_candidates` of one anchor pair's hypotheses (``first``, ``second``) for each third star (its
    two windows in ``windows``): the hypotheses that may hit for some third (first, second), may_hit (T, M'), and per
    third its (hypothesis, catalogue star) pairs, the hypotheses numbered among those kept (None: the tree decides)."""
    may_hit = np.ones((len(windows), first.size), dtype=bool)
    near: list[tuple[np.ndarray, np.ndarray] | None] = []
    second_columns = _columns_of(pairs.columns, second)
    for t, (with_first, with_second) in enumerate(windows):
        may_hit[t], hyp, stars = _pyramid_candidates(
            pairs.columns, first, second, with_first, with_second, second_columns
        )
        near.append(None if hyp is None else (hyp, stars))
    kept = np.flatnonzero(np.any(may_hit, axis=0))
    if kept.size == 0:
        return first[kept], second[kept], may_hit[:, kept], near
    position = np.empty(kept[-1] + 1, dtype=np.int64)
    position[kept] = np.arange(kept.size)  # a candidate's hypothesis may hit: it is kept
    near = [None if pair is None else (position[pair[0]], pair[1]) for pair in near]
    return first[kept], second[kept], may_hit[:, kept], near


def _best_hypothesis(
    b: np.ndarray,
    anchors: tuple[int, int],
    first: np.ndarray,
    second: np.ndarray,
    thirds: list[int],
    may_hit: np.ndarray,
    tree,
    tree_rows: np.ndarray,
    hit_chord: float,
    r: np.ndarray,
    mirrored: bool,
    near: list[tuple[np.ndarray, np.ndarray] | None] | None = None,
    r_frame: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`anchor_candidates` for one anchor pair (rows ``anchors`` of ``b``) against its catalogue pairs
    (``first``, ``second``: sky indices; ``r`` the sky's unit vectors) at one parity: the TRIAD hypotheses that put a
    third anchor star (``thirds``, tried where ``may_hit``) on a catalogue star, and of them the one whose predictions
    of the other stars hit catalogue stars most often, at least :data:`MIN_HITS` times: (rows into b, sky indices),
    or None. ``near``: per third star, the (hypothesis, catalogue star) pairs of :func:`_pyramid_candidates`, every
    star that can be within the hit chord of its prediction: their distances decide, as the tree's query would
    (within the chord: closer than it, the squared distance summed over x, y, z), instead of the tree (None: the
    tree decides). ``r_frame``: the catalogue side of the TRIAD attitudes (:func:`_triad_frame` of the pairs), the
    same at both parities."""
    i, j = anchors
    k = b.shape[0]
    others = np.array([m for m in range(k) if m not in (i, j)])
    bm = b * np.array([-1.0, 1.0, 1.0]) if mirrored else b
    r_frame = r_frame if r_frame is not None else _triad_frame(r[first], r[second])
    c_t = _triad_inverse(bm[i][None], bm[j][None], r[first], r[second], r_frame)
    # pyramid pruning: a hypothesis must first put one more anchor star on a catalogue star
    alive = np.zeros(first.size, dtype=bool)
    for m, may, pair in zip(thirds, may_hit, near or [None] * len(thirds), strict=True):
        ask = np.flatnonzero(may & ~alive)
        if ask.size and pair is None:
            dist, _ = tree.query((c_t @ bm[m])[ask], distance_upper_bound=hit_chord)
            alive[ask[np.isfinite(dist)]] = True
        elif ask.size:
            hyp, star = pair
            offset = c_t[hyp] @ bm[m] - r[star]  # the predictions of the hypotheses that ask alone
            within = offset[:, 0] ** 2 + offset[:, 1] ** 2 + offset[:, 2] ** 2 < hit_chord**2
            alive[hyp[within]] = True
    live = np.flatnonzero(alive)
    if live.size == 0:
        return None
    predicted = np.einsum("mij,kj->mki", c_t[live], bm[others])
    dist, idx = tree.query(predicted.reshape(-1, 3), distance_upper_bound=hit_chord)
    idx = idx.reshape(live.size, others.size)
    star = tree_rows[np.minimum(idx, tree_rows.size - 1)]
    # a hit on one of the anchors' own catalogue stars (a close double) is no evidence
    hits = np.isfinite(dist).reshape(live.size, others.size)
    hits &= (star != first[live][:, None]) & (star != second[live][:, None])
    count = hits.sum(axis=1)
    best = int(np.argmax(count))
    if count[best] < MIN_HITS:
        return None
    got = hits[best]
    h = live[best]
    rows = np.concatenate([[i, j], others[got]]).astype(np.int64)
    stars = np.concatenate([[first[h], second[h]], star[best][got]]).astype(np.int64)
    return rows, stars


#: Fallback matcher: the anchor pairs (one pair at one focal-length scale each) one frame may try in all, over the
#: scan of scales and both rounds; a frame that has not verified within them is reported as "no match within N anchor
#: pairs". The figure: every pair among the :data:`ANCHOR_STARS` brightest at the nominal scale (the likeliest, tried
#: as before the budget), then the three pairs among the three brightest at each other scanned scale (one false star
#: among those three still leaves a pair of true stars; if the three brightest have not given a verified match,
#: fainter anchors rarely do). The rounds at a known scale (pairs among the :data:`DEEP_ANCHOR_STARS` brightest, 66)
#: fit it whole: it cuts only scans, where a frame of noise spent minutes on the 1071 pairs of 51 scales.
MAX_ANCHOR_PAIRS = ANCHOR_STARS * (ANCHOR_STARS - 1) // 2 + 3 * (len(SCAN_SCALES) - 1)


def _anchor_schedule(
    k: int, n_anchor: int, skip: int, scales: tuple[float, ...]
) -> Iterator[tuple[float, list[tuple[int, int]]]]:
    """The order the fallback matcher tries anchor pairs (rows into the ``k`` brightest stars) in: (scale, pairs) to
    hand to :func:`anchor_candidates`. At the first (or only) scale, every pair among the first ``n_anchor`` with its
    second star at or after ``skip``, brightest first. Over the other scales of a scan, star by star: the pairs among
    the first three stars at every scale, then the pairs of the fourth star with the three before it at every scale,
    and so on, so that a budget (:data:`MAX_ANCHOR_PAIRS`) spent in this order keeps the brightest stars' pairs at
    every scale (the true scale may be the last one scanned) instead of every pair at the first scales."""
    n_stars = min(k, n_anchor)
    pairs = [(int(i), int(j)) for i, j in zip(*np.triu_indices(n_stars, 1), strict=True) if j >= skip]
    if pairs and scales:
        yield scales[0], pairs
    blocks = [[(i, j) for j in range(1, min(3, n_stars)) for i in range(j)]]  # the pairs among the first three
    blocks += [[(i, j) for i in range(j)] for j in range(3, n_stars)]
    for block in blocks:
        block = [(i, j) for i, j in block if j >= skip]
        if block:
            for scale in scales[1:]:
                yield scale, block


#: Fallback matcher: when no frame has been identified to tell how deep the camera sees, the catalogue depth is the
#: magnitude at which a field of the camera's size holds this many catalogue stars on average (Hp 8.0 on a 10 x 10 deg
#: field, 6.5 on 27 x 20 deg, 5.3 on 50 x 37 deg: a camera that sees a wider field is built for brighter stars, and
#: the pair index, which grows with the square of the stars within a field's diameter, stays ~100 MB).
FALLBACK_STARS_PER_FIELD = 90


def fallback_depth_mag(sky_mag: np.ndarray, field_sr: float) -> float:
    """The magnitude at which the catalogue (magnitudes ``sky_mag``, whole sky) holds on average
    :data:`FALLBACK_STARS_PER_FIELD` stars in a field of ``field_sr`` [sr]."""
    wanted = int(round(FALLBACK_STARS_PER_FIELD * 4.0 * math.pi / max(field_sr, 1e-9)))
    mags = np.sort(sky_mag[np.isfinite(sky_mag)])
    return float(mags[min(max(wanted, 1), mags.size) - 1])


#: Fallback matcher: catalogue depth beyond the 90th percentile of the magnitudes the engine identified in the
#: session (the extension step adds a few stars fainter than the camera's usual depth; the pair index grows with the
#: square of the star count, so they should not set it) [mag].
FALLBACK_MAG_MARGIN = 0.5
#: ... the percentile of the identified stars' magnitudes that margin is added to (above) [%].
FALLBACK_DEPTH_PERCENTILE = 90


def fallback_angle_rad(nominal: CameraParams) -> float:
    """How wide the own matcher's pairs go [rad]: the detector's diagonal at the smallest scanned scale."""
    width, height = nominal.image_size_px
    half_diagonal = 0.5 * math.hypot(width, height) / (nominal.focal_length_px * min(SCAN_SCALES))
    return 2.0 * math.atan(half_diagonal)


def prepare_cache(
    nominal: CameraParams, catalogue: Catalogue | None = None, maglim: float | None = None, use_engine: bool = True
) -> PairCache:
    """A :class:`PairCache` holding what identifying sessions of the camera ``nominal`` builds from the catalogue
    alone, built now rather than in the first call: the catalogue's index, the engine's pattern database at the
    nominal field and the own matcher's pair table as wide as identification can ask for this camera
    (:func:`fallback_angle_rad`) and as deep as it asks when the engine identified no frame (the field's depth,
    :func:`fallback_depth_mag`; a session whose engine-identified stars ask for up to :data:`FALLBACK_MAG_MARGIN`
    more has it built again: the deepest table at once would cost far more memory, docs/realsky.md "Where the speed
    stands"). Pass it as ``cache`` to ``identify_session`` or ``identify_iteratively``
    (:mod:`hostlink.images.identify`; the same results: a table cut from a larger one is the table built for the
    cut): for a user identifying many sessions of one camera, and for timing identification apart from its
    database, as a plate solver's database is built beforehand. ``catalogue``, ``maglim``, ``use_engine``: as those
    calls will be given them."""
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    check_field(nominal)
    cache = PairCache()
    if maglim is not None:
        catalogue = cache.bright(catalogue, maglim)
    sky = cache.sky(catalogue)
    if use_engine and solver_adapter.engine_available():
        fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, nominal.image_size_px[0])
        cache.database(catalogue, fov, maglim)
    depth = fallback_depth_mag(sky.mag, _field_sr(nominal))
    cache.pairs(sky, fallback_angle_rad(nominal), depth)
    return cache
