"""Robustness against misidentified stars, false matches and a poor nominal: a pre-pass, interstar voting, Huber
weights, residual gating.

0. Pre-pass (:func:`estimate_scale_and_parity`): the focal length from the identified stars' own interstar angles
   (a nominal off by a factor of 0.1 to 10 was tested, e.g. the pixel pitch of an unbinned detector: it starts where
   a good one would),
   and the parity (a mirrored image keeps every interstar angle but reverses the handedness of every star triple).
1. Voting (before any fit): interstar angles are invariant under the unknown attitude (seed 000 eq. 3), so a star
   whose angles to most other stars of its frame disagree with the catalogue's is misidentified. The tolerance is
   generous enough for an uncalibrated nominal camera (a relative focal-length error plus a few pixels).
2. Huber loss during the fit (IRLS weights), so what voting missed cannot pull the solution far.
3. Gating after convergence: residuals beyond ``gate`` robust sigmas are dropped and the fit is repeated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import (
    CalibrationData,
    angle_from_dot_rad,
    block_gram,
    count_blocks,
    frame_chunks,
    frame_slots,
    gram_matrices,
    pair_angles_at_rad,
)
from hostlink.calibration.prepass_sample import PREPASS_MAX_FRAMES, PREPASS_MAX_PAIRS, prepass_frames, prepass_rows
from onboard.camera import pixels_to_unit

#: Voting (:func:`vote_consistent_stars`): a pair agrees when |angle_b - angle_r| <= VOTE_REL_TOL * angle_r +
#: VOTE_ABS_TOL_RAD, and a star is consistent when it agrees with at least VOTE_MIN_AGREEMENT of the others.
VOTE_REL_TOL = 0.03
VOTE_ABS_TOL_RAD = 1e-3
VOTE_MIN_AGREEMENT = 0.5

#: Most stars whose frames' star pairs are worked on at once (voting, the pre-pass, the field's widest pair): bounds
#: the per-pair temporaries (Gram matrices, angles) to a few MB at 30 stars per frame (20 000 stars x 30 pairs x
#: 8 bytes each); the bundle's per-star passes use :data:`hostlink.calibration.model.DEFAULT_CHUNK_OBS`.
PAIR_BLOCK_OBS = 20_000

#: median |e| of a 2-D isotropic Gaussian with unit sigma per axis (Rayleigh median sqrt(2 ln 2)).
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True)
class _FramePairs:
    """The real star pairs (i < j) of the frames [f0, f1) of a data set, with all that does not depend on the
    camera: built once per chunk by :func:`_frame_pairs`, reused for every camera a pass tries. Pairs go frame by
    frame, and within a frame by second star, then first: (0, 1), (0, 2), (1, 2), (0, 3), ..., so the pairs of a
    frame of c stars are the first c (c - 1) / 2 of one list. Every use of them is a per-pair test, a count, a
    maximum or a sort, none of which depends on that order."""

    rows: slice  # the chunk's data rows
    slots: np.ndarray  # (n,) flat slot of each row in the padded (m * nmax) layout (frame * nmax + slot)
    counts: np.ndarray  # (m,) stars per frame
    pairs_per_frame: np.ndarray  # (m,) c (c - 1) / 2
    positions: np.ndarray  # (P,) flat positions of the pairs in the stacked (m, nmax, nmax) Gram matrices
    r: np.ndarray  # (m, nmax, 3) padded reference directions
    ang_r_rad: np.ndarray  # (P,) catalogue angles
    min_dot_r: float  # smallest catalogue dot product of two stars of one frame, the star itself included (<= 1)

    @property
    def nmax(self) -> int:
        return int(self.r.shape[1])


def _frame_pairs(data: CalibrationData, f0: int, f1: int) -> _FramePairs:
    """The :class:`_FramePairs` of frames [f0, f1) of ``data``: the padded layout of
    :func:`hostlink.calibration.data.frame_slots` and the catalogue angles of its real pairs (their Gram matrix
    entries, :func:`hostlink.calibration.data.pair_angles_at_rad`)."""
    rows, slot, slots, r, gram = _padded_gram(data, f0, f1)
    m, nmax = r.shape[:2]
    counts = np.diff(data.frame_starts[f0 : f1 + 1])
    second_slot, first_slot = np.tril_indices(nmax, -1)  # (1, 0), (2, 0), (2, 1), (3, 0), ...: by second star
    per_frame = counts * (counts - 1) // 2
    upper = first_slot * nmax + second_slot  # a frame of nmax stars: its pairs' positions (one frame: all of them)
    if m == 1:
        positions = upper
    else:
        k = np.arange(int(per_frame.sum())) - np.repeat(np.cumsum(per_frame) - per_frame, per_frame)
        positions = np.repeat(np.arange(m) * (nmax * nmax), per_frame) + upper[k]
    gram = gram.reshape(-1)
    dots = gram[positions]
    diagonal = gram[slots * nmax + slot]
    return _FramePairs(
        rows=rows,
        slots=slots,
        counts=counts,
        pairs_per_frame=per_frame,
        positions=positions,
        r=r,
        ang_r_rad=angle_from_dot_rad(dots),
        min_dot_r=min(1.0, float(np.min(dots, initial=1.0)), float(np.min(diagonal, initial=1.0))),
    )


def _padded_gram(data: CalibrationData, f0: int, f1: int):
    """The frames [f0, f1) of ``data`` in the padded layout of :func:`hostlink.calibration.data.frame_slots`: their
    data rows, each row's slot in its frame and flat slot (frame * nmax + slot), the catalogue directions
    (m, nmax, 3) with zero rows as padding, and their Gram matrices (m, nmax, nmax)."""
    _, frame, slot, nmax = frame_slots(data.frame_starts, f0, f1)
    rows = slice(int(data.frame_starts[f0]), int(data.frame_starts[f1]))
    slots = frame * nmax + slot
    r = _padded(slots, data.r[rows], f1 - f0, nmax)
    return rows, slot, slots, r, gram_matrices(r)


def max_pair_angle_rad(data: CalibrationData, chunk_obs: int = PAIR_BLOCK_OBS) -> float:
    """The largest catalogue angle between two stars of one frame [rad] (the field the data span; 0 for frames of
    one star): the angle, monotone in the dot product, of the smallest dot product of the Gram matrices of
    :func:`_frame_pairs`, the star itself included (its ``min_dot_r``, without the angles of every pair)."""
    min_dot = 1.0
    for f0, f1 in frame_chunks(data.frame_starts, chunk_obs):
        _, _, slots, r, gram = _padded_gram(data, f0, f1)
        # the padding's zero rows give dot products 0: only the real stars' pairs i <= j count (_frame_pairs's)
        real = np.bincount(slots, minlength=r.shape[0] * r.shape[1]).reshape(r.shape[:2]) > 0  # (m, nmax)
        use = real[:, :, None] & real[:, None, :] & np.triu(np.ones(gram.shape[1:], dtype=bool))
        min_dot = min(min_dot, float(np.min(gram, where=use, initial=1.0)))
    return float(angle_from_dot_rad(np.float64(min_dot)))


def _padded(slots: np.ndarray, v: np.ndarray, m: int, nmax: int) -> np.ndarray:
    """Rows ``v`` (n, 3) at their flat ``slots`` of an (m, nmax, 3) array of zeros (the padding)."""
    out = np.zeros((m * nmax, 3))
    out[slots] = v
    return out.reshape(m, nmax, 3)


def _padded_directions(pairs: _FramePairs, b: np.ndarray) -> np.ndarray:
    """The chunk's measured directions (rows of ``b`` (N, 3), the whole data set's) in the padded layout."""
    return _padded(pairs.slots, b[pairs.rows], *pairs.r.shape[:2])


def vote_consistent_stars(
    data: CalibrationData,
    b: np.ndarray,
    rel_tol: float = VOTE_REL_TOL,
    abs_tol_rad: float = VOTE_ABS_TOL_RAD,
    min_agreement: float = VOTE_MIN_AGREEMENT,
    chunk_obs: int = PAIR_BLOCK_OBS,
) -> np.ndarray:
    """(N,) bool: stars whose interstar angles agree with the catalogue for at least ``min_agreement`` of the other
    stars of their frame. ``b`` are measured directions from the nominal camera.

    A pair agrees when |angle_b - angle_r| <= rel_tol * angle_r + abs_tol_rad (defaults: a nominal focal length
    within 3 %, and 1 mrad for principal-point and distortion errors of a few pixels at typical focal lengths).
    Frames go in blocks of one star count of at most ``chunk_obs`` stars, unpadded (one camera over a session), so
    the work is vectorised and bounded. :func:`vote_of_table` is the same test and count (:func:`_disagreeing`,
    :func:`_consistent`) on padded chunks whose catalogue side serves several cameras: the same stars kept."""
    return consistent_stars_and_field(data, b, rel_tol, abs_tol_rad, min_agreement, chunk_obs)[0]


def consistent_stars_and_field(
    data: CalibrationData,
    b: np.ndarray,
    rel_tol: float = VOTE_REL_TOL,
    abs_tol_rad: float = VOTE_ABS_TOL_RAD,
    min_agreement: float = VOTE_MIN_AGREEMENT,
    chunk_obs: int = PAIR_BLOCK_OBS,
) -> tuple[np.ndarray, float]:
    """:func:`vote_consistent_stars`, and the largest catalogue angle between two stars of one frame [rad]
    (:func:`max_pair_angle_rad`, from the Gram matrices the vote computes anyway).

    The frames go in blocks of one star count n (:func:`hostlink.calibration.data.count_blocks`, at most
    ``chunk_obs`` stars): each block's catalogue and measured directions are (m, n, 3) stacks whose Gram matrices
    hold every pair's dot product without padding (half the entries of frames padded to their chunk's largest
    count, for 10-30 stars per frame), and the pairs i < j are the same entries of every frame of the block."""
    keep = np.zeros(data.n_obs, dtype=bool)
    min_dot = 1.0
    for rows, m, n in count_blocks(data.frame_starts, chunk_obs):
        gram_r = block_gram(data.r, rows, m, n)
        # the star itself included, as in _frame_pairs: a frame of one star spans no angle (rounding aside)
        min_dot = min(min_dot, float(np.min(gram_r, initial=1.0)))
        if n < 2:
            continue  # no other star to agree with: not consistent
        first, second = np.triu_indices(n, 1)
        upper = first * n + second
        ang_r = angle_from_dot_rad(np.take(gram_r, upper, axis=1))
        ang_b = angle_from_dot_rad(np.take(block_gram(b, rows, m, n), upper, axis=1))
        frame, pair = np.divmod(np.flatnonzero(_disagreeing(ang_b, ang_r, rel_tol, abs_tol_rad)), upper.size)
        misses = np.bincount(frame * n + first[pair], minlength=m * n)  # a pair counts against both its stars
        misses += np.bincount(frame * n + second[pair], minlength=m * n)
        keep[rows] = _consistent(misses, n - 1, min_agreement)
    return keep, float(angle_from_dot_rad(np.float64(min_dot)))


def pair_table(data: CalibrationData, chunk_obs: int = PAIR_BLOCK_OBS) -> list[_FramePairs]:
    """The catalogue side of every star pair of ``data`` (:func:`_frame_pairs` of each chunk with a pair), built once
    for what a caller asks of the same stars: :func:`estimate_scale_of_table`, :func:`vote_of_table` and
    :func:`triple_handedness_of_table` give what :func:`estimate_scale`, :func:`vote_consistent_stars` and
    :func:`triple_handedness` give (the same Gram entries, angles and tests), each of which builds its own."""
    return _chunk_pairs(data, chunk_obs, 2)


def vote_of_table(
    table: list[_FramePairs],
    b: np.ndarray,
    n_obs: int,
    rel_tol: float = VOTE_REL_TOL,
    abs_tol_rad: float = VOTE_ABS_TOL_RAD,
    min_agreement: float = VOTE_MIN_AGREEMENT,
) -> np.ndarray:
    """:func:`vote_consistent_stars` of the ``n_obs`` stars of a :func:`pair_table` (measured directions ``b``), its
    test and count (:func:`_disagreeing`, :func:`_consistent`) on the table's padded chunks, whose catalogue angles
    serve every camera a caller tries (identification's scale, vote and triples); the same stars kept."""
    keep = np.zeros(n_obs, dtype=bool)
    for pairs in table:
        ang_b = pair_angles_at_rad(_padded_directions(pairs, b), pairs.positions)
        nmax, size = pairs.nmax, pairs.r.shape[0] * pairs.nmax
        first, second = np.divmod(pairs.positions[_disagreeing(ang_b, pairs.ang_r_rad, rel_tol, abs_tol_rad)], nmax)
        second += first - first % nmax  # first: the first star's flat slot; second: the second's slot, made flat
        misses = (np.bincount(first, minlength=size) + np.bincount(second, minlength=size))[pairs.slots]
        keep[pairs.rows] = _consistent(misses, np.repeat(pairs.counts - 1, pairs.counts), min_agreement)
    return keep


def _disagreeing(ang_b: np.ndarray, ang_r: np.ndarray, rel_tol: float, abs_tol_rad: float) -> np.ndarray:
    """(P,) bool: the vote's test fails, |angle_b - angle_r| > rel_tol * angle_r + abs_tol_rad (NaN fails)."""
    return ~(np.abs(ang_b - ang_r) <= rel_tol * ang_r + abs_tol_rad)


def _consistent(misses: np.ndarray, others, min_agreement: float) -> np.ndarray:
    """(n,) bool: a star agrees with at least ``min_agreement`` of the ``others`` stars of its frame, given the
    ``misses`` among them (exact integer counts); one with no other star is not consistent."""
    return (others > 0) & ((others - misses) / np.maximum(others, 1) >= min_agreement)


def robust_sigma_2d(residual_norm: np.ndarray) -> float:
    """Per-axis sigma from norms of 2-D residuals: median / sqrt(2 ln 2) (50 % breakdown, exact for Gaussians)."""
    if residual_norm.size == 0:
        return float("nan")
    return float(np.median(residual_norm) / RAYLEIGH_MEDIAN)


def huber_weights(residual_norm: np.ndarray, scale: float, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss on the norm of a residual: 1 inside k * scale, k * scale / |e| outside."""
    z = residual_norm / (k * scale)
    return np.where(z <= 1.0, 1.0, 1.0 / np.maximum(z, 1e-300))


def huber_rho(residual_norm: np.ndarray, scale: float, k: float) -> np.ndarray:
    """rho(|e|) of each residual: t^2 / 2 inside c = k * scale and c |t| - c^2 / 2 outside (Huber 1964); t^2 / 2
    everywhere for an infinite scale (plain least squares)."""
    t = residual_norm
    if not np.isfinite(scale):
        return 0.5 * t * t
    c = k * scale
    return np.where(t <= c, 0.5 * t * t, c * t - 0.5 * c * c)


#: Pre-pass: width of the densest-window (mode) search on log(angle ratio). The search is not bounded (a factor of
#: 0.1 to 10 was tested); the window holds the pairs of a field whose distortion changes the local scale by ~1 %, and
#: the iteration through the rescaled camera narrows what is left.
SCALE_MODE_WINDOW = 0.02
#: Pre-pass: pairs shorter than this fraction of a frame's longest pair carry their centroid errors as a large
#: relative angle error; they do not vote on the scale.
SCALE_MIN_PAIR_FRACTION = 0.2
#: Pre-pass: triples whose spanned volume |det[r1 r2 r3]| is below this fraction of the largest of their frame are
#: too close to collinear for the sign of the determinant to be trusted.
PARITY_MIN_VOLUME_FRACTION = 0.05
#: Pre-pass: triples of catalogue directions spanning less than this volume |det[r1 r2 r3]| are degenerate whatever
#: their frame's largest (two stars identified as the same catalogue star): the triple product of unit vectors has a
#: rounding error of ~1e-15, and three real stars 1.4 urad apart (far below a pixel) still span 1e-12.
PARITY_MIN_VOLUME = 1e-12
#: Pre-pass: most random triples per frame examined for the parity.
PARITY_TRIPLES_PER_FRAME = 40


@dataclass(frozen=True)
class ScaleParity:
    """What the identified stars say about the nominal camera before any fit (:func:`estimate_scale_and_parity`).

    scale: F_true / F_nominal, the focal-length ratio (1.0 when no pair could vote).
    n_pairs: star pairs that voted on the scale (inside the densest window).
    mirrored_fraction: of the triples of consistent stars, the fraction whose handedness in the camera frame is
    opposite to the sky's (0 for a correct detector, 1 for a mirrored one); NaN when no triple qualified.
    n_triples: triples that voted on the parity.
    """

    scale: float
    n_pairs: int
    mirrored_fraction: float
    n_triples: int

    @property
    def mirrored(self) -> bool:
        return bool(self.n_triples > 0 and self.mirrored_fraction > 0.5)


def _densest_window(values: np.ndarray, width: float) -> tuple[float, int]:
    """Median of the values inside the window of the given width that holds the most of them (a mode estimate:
    unlike the median it survives more than 50 % of outliers when they are spread out), and that count; of equally
    full windows the first. The windows [v_i, v_i + width] of the sorted values are counted exactly only in the
    blocks of :data:`DENSEST_BLOCK` starts that can hold the fullest (:func:`_densest_start`)."""
    v = np.sort(values)
    i, upper = _densest_start(v, width)
    return float(np.median(v[i:upper])), upper - i


#: :func:`_densest_start` bounds the windows' counts by blocks of this many sorted values: few enough for the blocks
#: about the mode to be counted start by start cheaply, enough for one bound (a binary search) to stand for many.
DENSEST_BLOCK = 64


def _densest_start(v: np.ndarray, width: float) -> tuple[int, int]:
    """(i, upper): the first i maximising the count upper - i of the sorted values ``v`` in [v_i, v_i + width]
    (upper: the number of values <= v_i + width), as an argmax over every i gives. upper is non-decreasing in i, so
    in a block of starts [i0, i1) no count exceeds upper(i1 - 1) - i0; the count at each block's first start is
    reached, and only the blocks whose bound reaches the largest of those are counted start by start (a handful of
    blocks about the mode instead of a binary search per value: docs/realsky.md, "Identification alone")."""
    n = v.size
    if n <= 4 * DENSEST_BLOCK:  # a few blocks: every start counted costs no more
        upper = np.searchsorted(v, v + width, side="right")
        i = int(np.argmax(upper - np.arange(n)))
        return i, int(upper[i])
    first = np.arange(0, n, DENSEST_BLOCK)
    last = np.minimum(first + DENSEST_BLOCK - 1, n - 1)
    reached = np.searchsorted(v, v[first] + width, side="right") - first
    bound = np.searchsorted(v, v[last] + width, side="right") - first
    blocks = np.flatnonzero(bound >= reached.max())
    starts = (first[blocks, None] + np.arange(DENSEST_BLOCK)).ravel()
    starts = starts[starts < n]
    upper = np.searchsorted(v, v[starts] + width, side="right")
    k = int(np.argmax(upper - starts))
    return int(starts[k]), int(upper[k])


def _long_pairs(pairs: _FramePairs) -> tuple[np.ndarray, np.ndarray]:
    """The Gram positions and catalogue angles of the pairs whose catalogue angle is at least
    :data:`SCALE_MIN_PAIR_FRACTION` of their frame's longest (and not zero), in order."""
    per_frame = pairs.pairs_per_frame
    has = per_frame > 0
    longest = np.zeros(per_frame.size)
    if np.any(has):
        longest[has] = np.maximum.reduceat(pairs.ang_r_rad, (np.cumsum(per_frame) - per_frame)[has])
    ang_r = pairs.ang_r_rad
    use = (ang_r >= SCALE_MIN_PAIR_FRACTION * np.repeat(longest, per_frame)) & (ang_r > 0)
    return pairs.positions[use], ang_r[use]


def _pair_log_ratios(chunks: list[_FramePairs], long: list[tuple[np.ndarray, np.ndarray]], b: np.ndarray) -> np.ndarray:
    """log(angle_b / angle_r) over every pair of every frame whose catalogue angle is at least
    :data:`SCALE_MIN_PAIR_FRACTION` of its frame's longest (``long``, :func:`_long_pairs`; small angles:
    angle_b / angle_r = F_true / F_nominal), for measured directions ``b`` (N, 3)."""
    out = []
    for pairs, (positions, ang_r) in zip(chunks, long, strict=True):
        ang_b = pair_angles_at_rad(_padded_directions(pairs, b), positions)
        use = ang_b > 0
        if not np.all(use):
            ang_b, ang_r = ang_b[use], ang_r[use]
        out.append(np.log(ang_b / ang_r))
    return np.concatenate(out) if out else np.zeros(0)


def _chunk_pairs(data: CalibrationData, chunk_obs: int, min_stars: int) -> list[_FramePairs]:
    """:func:`_frame_pairs` of every chunk of ``data`` (:func:`hostlink.calibration.data.frame_chunks`) whose
    largest frame has at least ``min_stars`` stars."""
    chunks = [_frame_pairs(data, f0, f1) for f0, f1 in frame_chunks(data.frame_starts, chunk_obs)]
    return [c for c in chunks if c.nmax >= min_stars]


def estimate_scale(data: CalibrationData, theta: np.ndarray, chunk_obs: int = PAIR_BLOCK_OBS) -> tuple[float, int]:
    """F_true / F_nominal from the identified stars themselves: the interstar angles measured through the camera
    ``theta`` (model vector, F in px) against the catalogue's. For a pinhole, tan(angle) scales as 1 / F for pairs
    through the boresight, so the ratio angle_b / angle_r of every long pair votes for F_true / F_nominal; the
    densest 2 % window of log ratios (:data:`SCALE_MODE_WINDOW`) wins, so misidentified stars do not pull it. The
    estimate is iterated three times (each through the rescaled camera) to remove the wide-field nonlinearity; the
    catalogue angles are computed once and kept for them (16 bytes per pair: the pre-pass calls this on at most
    :data:`PREPASS_MAX_FRAMES` frames). Returns (scale, number of pairs in the winning window); (1.0, 0) when no
    pair votes."""
    return estimate_scale_of_table(data, pair_table(data, chunk_obs), theta)


def estimate_scale_of_table(data: CalibrationData, chunks: list[_FramePairs], theta: np.ndarray) -> tuple[float, int]:
    """:func:`estimate_scale` of ``data`` from its :func:`pair_table` (``chunks``), computed once for the
    iterations."""
    theta = np.array(theta, dtype=np.float64)
    long = [_long_pairs(c) for c in chunks]
    scale, n = 1.0, 0
    for _ in range(3):
        ratios = _pair_log_ratios(chunks, long, pixels_to_unit(data.x_px, data.y_px, theta))
        if ratios.size == 0:
            return 1.0, 0
        log_step, n = _densest_window(ratios, SCALE_MODE_WINDOW)
        step = math.exp(log_step)
        scale *= step
        theta[0] *= step
        if abs(log_step) < 1e-5:  # 0.001 %: far inside the voting tolerance, and the fit refines it anyway
            break
    return scale, n


def triple_handedness(
    data: CalibrationData, b: np.ndarray, consistent: np.ndarray, seed: int = 0, chunk_obs: int = PAIR_BLOCK_OBS
) -> tuple[int, int]:
    """(triples with opposite handedness, triples examined): for up to :data:`PARITY_TRIPLES_PER_FRAME` random
    triples of ``consistent`` stars per frame, sign(det[b1 b2 b3]) against sign(det[r1 r2 r3]). A rotation keeps
    the sign of every triple product; a mirror (one flipped image axis) reverses it, while it keeps every interstar
    angle, so only this test finds it. Triples too close to collinear (:data:`PARITY_MIN_VOLUME_FRACTION`) or
    degenerate (:data:`PARITY_MIN_VOLUME`) are skipped. Deterministic for a given ``seed``."""
    return triple_handedness_of_table(_chunk_pairs(data, chunk_obs, 3), b, consistent, seed)


def triple_handedness_of_table(
    table: list[_FramePairs], b: np.ndarray, consistent: np.ndarray, seed: int = 0
) -> tuple[int, int]:
    """:func:`triple_handedness` from a :func:`pair_table` (its chunks of at least 3 stars)."""
    rng = np.random.default_rng(seed)
    opposite = total = 0
    k = PARITY_TRIPLES_PER_FRAME
    for pairs in (c for c in table if c.nmax >= 3):
        pb = _padded_directions(pairs, b)
        m, nmax = pairs.r.shape[:2]
        valid = np.zeros(m * nmax, dtype=bool)
        valid[pairs.slots] = consistent[pairs.rows]
        valid_rows = np.flatnonzero(valid)  # padded rows of the consistent stars, frame by frame
        if valid_rows.size == 0:
            continue
        n_valid = np.count_nonzero(valid.reshape(m, nmax), axis=1)
        ok = np.broadcast_to((n_valid >= 3)[:, None], (m, k)).copy()
        first = np.cumsum(n_valid) - n_valid
        picks = random_triples(rng, n_valid, k) + first[None, :, None]
        flat = valid_rows[np.minimum(picks, valid_rows.size - 1)]  # (3, m, k) padded rows (frames with < 3: not ok)
        det_b = _triple_product(pb.reshape(-1, 3), flat)
        det_r = _triple_product(pairs.r.reshape(-1, 3), flat)
        biggest = np.max(np.where(ok, np.abs(det_r), 0.0), axis=1, keepdims=True)
        ok &= np.abs(det_r) >= PARITY_MIN_VOLUME_FRACTION * biggest
        ok &= np.abs(det_r) > PARITY_MIN_VOLUME
        opposite += int(np.count_nonzero(ok & (np.sign(det_b) != np.sign(det_r))))
        total += int(np.count_nonzero(ok))
    return opposite, total


def random_triples(rng: np.random.Generator, n: np.ndarray, k: int) -> np.ndarray:
    """(3, m, k) indices of k uniformly random triples of distinct items out of each frame's n items (n >= 3; the
    entries of frames with fewer are in [0, 3) and meaningless): i of n, j of the n - 1 others, h of the n - 2 left,
    each skipping the ones drawn before it. Their order does not matter to the parity (a permutation flips det_b and
    det_r alike)."""
    u = rng.random((3, n.size, k))
    i, j, h = (
        np.minimum((u[a] * np.maximum(n - a, 1)[:, None]).astype(np.int64), np.maximum(n - a - 1, 0)[:, None])
        for a in range(3)
    )
    j += j >= i
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    h += h >= lo
    h += h >= hi
    return np.stack([i, j, h])


def _triple_product(v: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """det[v_i v_j v_k] = v_i . (v_j x v_k) for each triple of rows (i, j, k) of ``v`` (n, 3) in ``idx`` (3, ...)."""
    x, y, z = np.ascontiguousarray(v.T)  # coordinates, each gathered into contiguous arrays
    i, j, k = idx
    yj, zj, yk, zk = y[j], z[j], y[k], z[k]
    xj, xk = x[j], x[k]
    return x[i] * (yj * zk - zj * yk) + y[i] * (zj * xk - xj * zk) + z[i] * (xj * yk - yj * xk)


def estimate_scale_and_parity(data: CalibrationData, theta: np.ndarray, chunk_obs: int = PAIR_BLOCK_OBS) -> ScaleParity:
    """The pre-pass before voting (:func:`estimate_scale`, then :func:`triple_handedness` over the stars that
    the interstar vote at the rescaled focal length finds consistent), on at most :data:`PREPASS_MAX_FRAMES`
    evenly spaced frames (:func:`prepass_frames`; the chunked path gathers the same frames from its chunks and
    calls :func:`scale_and_parity_of_sample`)."""
    if data.n_frames > PREPASS_MAX_FRAMES:
        frames = np.zeros(data.n_frames, dtype=bool)
        frames[prepass_frames(data.n_frames)] = True
        data = data.select(frames[data.frame_index()], min_stars=1)[0]
    return scale_and_parity_of_sample(data, theta, chunk_obs)


def scale_and_parity_of_sample(
    data: CalibrationData, theta: np.ndarray, chunk_obs: int = PAIR_BLOCK_OBS
) -> ScaleParity:
    """The pre-pass of :func:`estimate_scale_and_parity` on frames already sampled, on at most
    :data:`PREPASS_MAX_PAIRS` of their star pairs (:func:`prepass_rows`)."""
    keep = prepass_rows(data.frame_starts, PREPASS_MAX_PAIRS)  # read at the call: a test may lower it
    if keep is not None:
        data = data.select(keep, min_stars=1)[0]
    table = pair_table(data, chunk_obs)  # the catalogue side of every pair once: the scale, the vote, the triples
    scale, n_pairs = estimate_scale_of_table(data, table, theta)
    theta_s = np.array(theta, dtype=np.float64)
    theta_s[0] *= scale
    b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    consistent = vote_of_table(table, b, data.n_obs)
    opposite, total = triple_handedness_of_table(table, b, consistent)
    return ScaleParity(scale, n_pairs, opposite / total if total else float("nan"), total)
