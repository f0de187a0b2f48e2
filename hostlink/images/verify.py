"""Verification of a proposal (:mod:`hostlink.images.identify`, module docstring steps 2 and 4): the interstar vote,
the parity from star triples, the frame's own focal length, radial terms and principal point refined on its verified
stars (:func:`_refine_radial`), and the residual gate that drops the pairs the refined camera does not fit. A
proposal under a strong lens the nominal does not know, which no single scale verifies, gets its radial term k1
searched with the scale first (:func:`_radial_search`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import build_data
from hostlink.calibration.robust import (
    estimate_scale_of_table,
    pair_table,
    triple_handedness_of_table,
    vote_consistent_stars,
    vote_of_table,
)
from hostlink.images.skyindex import _mirror_x
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.camera import pixels_to_unit

#: Verification: relative interstar-angle tolerance after the scale is estimated. Unknown radial distortion of a
#: few pixels at the edge of a 1000 px detector changes a long pair's angle by a few 1e-3.
VERIFY_REL_TOL = 0.005


#: Verification: absolute interstar tolerance [px, converted to rad by the estimated focal length]: centroid
#: noise of real faint stars (0.3-1 px) plus the unmodelled distortion of a short pair.
VERIFY_ABS_TOL_PX = 3.0


#: Verification: fraction of the other candidates of its frame a star must agree with (a misidentified star agrees
#: with almost none; a true one with all true ones, so it passes while up to 30 % of its frame is wrong).
VERIFY_MIN_AGREEMENT = 0.7


#: Triples of verified stars must agree on the parity at least this often (1.0 for a clean frame; a near-collinear
#: triple with centroid noise can flip, so not all are required).
PARITY_MIN_AGREEMENT = 0.9


@dataclass(frozen=True)
class _Verified:
    keep: np.ndarray  # (K,) bool over the candidates
    mirrored: bool
    scale: float
    parity_agreement: float
    attitude: np.ndarray | None
    residual_rad: np.ndarray | None
    #: the camera vector the attitude and residuals are of: the nominal at ``scale``, its focal length and radial
    #: term refined on the frame's verified stars when they are enough (:func:`_refine_radial`)
    theta: np.ndarray | None = None


#: :func:`_refine_radial` needs at least this many verified stars (two parameters beyond the attitude's three, with
#: room for the centroid noise to average).
REFINE_MIN_STARS = 10


REFINE_ITERATIONS = 3


#: ... and k2 too from this many (a wide lens's distortion is not a pure cube of the radius).
REFINE_K2_STARS = 20


#: ... and the principal point from this many: a strong distortion about the nominal's centre when the lens's is some
#: pixels away misplaces the edge stars by tens of pixels (a 20-px offset under 12 % of corner distortion: 10-40 px
#: at the corners of the rendered wide set, where round 1 then named 1 % of its stars wrongly); with the radial terms
#: pinned by many stars the centre separates from the attitude's rotation.
REFINE_CENTRE_STARS = 40


REFINE_CENTRE_STEP_PX = 0.01


#: :func:`_refine_radial` fits k1 only when the 10th to 90th percentiles of its stars' squared radii span this fraction
#: of the 90th (a disc about the centre spans 0.9, a ring does not) or all of them this fraction of the corner's, and
#: k2 only when the percentiles span
#: :data:`REFINE_K2_SPAN` of the corner's squared radius (0.65 for stars spread over a square detector): simulated
#: 50-deg mustache frames whose proposals verified 26-104 stars in a ring (0.3-0.58 of the corner's r^2) fitted f 15 %
#: short with k1 of the wrong sign, or k1 2.5 times too strong, and the frame was lost.
REFINE_K1_SPAN = 0.5


REFINE_K2_SPAN = 0.35


#: Index of k1 in the camera vector (ESTIMATE_NAMES: f, cx, cy, then the distortion keys, k1 first).
_K1 = 3


def _refine_radial(
    x_px: np.ndarray,
    y_px: np.ndarray,
    r: np.ndarray,
    c: np.ndarray,
    theta: np.ndarray,
    r_corner_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The frame's own focal length and radial terms k1 (and k2 from :data:`REFINE_K2_STARS` stars): Gauss-Newton on
    sum |b(x, y; f, k1, k2, and the principal point from :data:`REFINE_CENTRE_STARS`) - C r|^2 jointly with a small
    rotation of the attitude (without it a shift of the centre, which is nearly a rotation, has no direction to go),
    derivatives by forward differences of :func:`onboard.camera.pixels_to_unit`, the attitude C refitted by Markley's
    SVD after each step. A wide lens's unmodelled distortion, which grows as the
    cube of the radius and faster, is then out of the predictions of the frame's other stars and out of the
    interstar angles its later candidates are verified by, and the match radius can follow the centroid noise
    instead of the lens. The radial terms only when the stars' squared radii span enough of the
    corner's (``r_corner_px``): stars in a ring alone (a proposal's first verified ones) cannot tell the focal length
    from distortion, and a fit of both there bends the rest of the field away. Returns
    (theta, C); the given ones when no step lowers the residual."""
    b_now = pixels_to_unit(x_px, y_px, theta)  # b through ``current``, computed once per step
    best = (theta, c, float(np.sum((b_now - r @ c.T) ** 2)))
    current, att = np.array(theta, dtype=np.float64), c
    r_max2 = float(np.max((x_px - theta[1]) ** 2 + (y_px - theta[2]) ** 2))
    steps = {0: 1e-6 * current[0]}
    r2 = (x_px - theta[1]) ** 2 + (y_px - theta[2]) ** 2
    low, high = np.percentile(r2, [10.0, 90.0])
    if float(high - low) >= REFINE_K1_SPAN * float(high) or float(np.ptp(r2)) >= REFINE_K1_SPAN * r_corner_px**2:
        steps[_K1] = 1e-4 / max(r_max2, 1.0)  # 1e-4 of the outermost star's radius
        if x_px.size >= REFINE_K2_STARS and float(high - low) >= REFINE_K2_SPAN * r_corner_px**2:
            steps[_K1 + 1] = 1e-4 / max(r_max2, 1.0) ** 2
    if x_px.size >= REFINE_CENTRE_STARS:
        steps[1] = steps[2] = REFINE_CENTRE_STEP_PX
    for _ in range(REFINE_ITERATIONS):
        b = b_now
        cr = r @ att.T
        residual = (b - cr).ravel()
        columns = []
        for index, step in steps.items():
            shifted = current.copy()
            shifted[index] += step
            columns.append(((pixels_to_unit(x_px, y_px, shifted) - b) / step).ravel())
        # the attitude's small rotation phi: C -> (I - [phi x]) C moves b - C r by -(C r) x phi
        for axis in np.eye(3):
            columns.append(-np.cross(cr, axis).ravel())
        jac = np.stack(columns, axis=1)
        norm = np.linalg.norm(jac, axis=0)
        if not np.all(norm > 0):
            break
        delta = np.linalg.lstsq(jac / norm, -residual, rcond=None)[0] / norm
        for (index, _), d in zip(steps.items(), delta[:-3], strict=True):
            current[index] += d
        b_now = pixels_to_unit(x_px, y_px, current)
        try:
            att = attitude_from_vectors(b_now, r)
        except DegenerateGeometry:
            break
        cost = float(np.sum((b_now - r @ att.T) ** 2))
        if cost < best[2]:
            best = (current.copy(), att, cost)
    return best[0], best[1]


#: The residual pattern's gate: a verified star whose residual after the frame's own refinement exceeds this many times
#: the median residual of the frame's verified stars, and at least :data:`RESIDUAL_GATE_MIN_PX`, is not that star (for
#: a 2-D Gaussian residual 8 medians are 9.4 sigma: no true star is lost to noise; a model still short of the lens at
#: the field edge leaves its true stars there at a few medians). The interstar vote passes a wrong pair whose error
#: is within its tolerance of most pairs; on a wide field that tolerance (0.5 % of a 1000-px pair) is 5 px, and the
#: rendered wide set's round 1 named edge stars 10-40 px from their true place.
RESIDUAL_GATE_MEDIANS = 8.0


RESIDUAL_GATE_MIN_PX = 2.0


#: Gate and refit at most this many times (each refit without the worst lets the next gate see the rest).
RESIDUAL_GATE_ROUNDS = 4


def _residual_outliers(residual_px: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(K,) bool: the residuals [px] beyond the gate (:data:`RESIDUAL_GATE_MEDIANS`) set by the ``keep`` ones."""
    gate = max(RESIDUAL_GATE_MEDIANS * float(np.median(residual_px[keep])), RESIDUAL_GATE_MIN_PX)
    return residual_px > gate


#: Pruning a matcher's proposal: a star agreeing with fewer than this fraction of the others is dropped, and the vote
#: repeated over the rest, until none is dropped (true stars then form the majority the final vote needs).
PRUNE_MIN_AGREEMENT = 0.5


#: :func:`_radial_search`: the k1 tried, as the radial term's change of the radius at the corner (k1 r_corner^2): from
#: a 30 % barrel to a 30 % pincushion (beyond, a fisheye, which identification refuses) in steps of 2 %, finer
#: than the plateau of k1 over which a strongly distorted frame's vote keeps most of its proposal (docs/realsky.md,
#: "Verification under a strong unknown lens").
RADIAL_SEARCH_CORNER = np.arange(-0.30, 0.30 + 1e-9, 0.02)


#: :func:`_radial_search` runs when the vote at the nominal's radial terms keeps fewer than this fraction of the
#: candidates (a proposal of mostly true stars keeps most; an unknown strong lens lets few agree at any one scale) ...
RADIAL_SEARCH_BELOW = 0.5


#: ... and for at most this many candidates (each k1 costs a scale estimate and a vote over their n^2 / 2 pairs: a
#: proposal's hundred or so, not an extension round's thousands).
RADIAL_SEARCH_MAX_STARS = 400


def _radial_search(data, table, theta: np.ndarray, r_corner_px: float) -> tuple[np.ndarray, float, np.ndarray]:
    """(camera vector, scale, keep) of the k1 that verifies the most candidates: for each added k1 = c /
    r_corner_px^2 (c in :data:`RADIAL_SEARCH_CORNER`), the scale from the pairs through that lens
    (:func:`hostlink.calibration.robust.estimate_scale_of_table`) and the vote at it; of equal counts the smallest
    |c|. The focal-length scale alone cannot absorb a strong radial term the nominal lacks: measured through
    x_d = x_u (1 + k1 r_u^2 + k2 r_u^4) (seed 000 eq. 7) a pair's angle shrinks by about the mean of k1 r^2 + k2 r^4
    over its two ends, 0 to 12 % across the 50-deg mustache lens, so no single scale puts 70 % of a frame's pairs
    within the vote's 0.5 %; the long pairs the scale is estimated from lie farthest out and pull it short (0.908
    for a true 0.962 on a 55-deg frame; docs/realsky.md, "Large frames"). k1 fitted jointly with the scale takes
    out the cube of the radius, the bulk of it; the verified stars then refine f, k1, k2 and the centre
    (:func:`_refine_radial`)."""
    n = data.x_px.shape[0]
    best = None
    for corner in sorted(RADIAL_SEARCH_CORNER, key=abs):
        theta_k = np.array(theta, dtype=np.float64)
        theta_k[_K1] += corner / r_corner_px**2
        scale, n_pairs = estimate_scale_of_table(data, table, theta_k)
        if n_pairs == 0:
            continue
        theta_k[0] *= scale
        b = pixels_to_unit(data.x_px, data.y_px, theta_k)
        keep = vote_of_table(
            table,
            b,
            n,
            rel_tol=VERIFY_REL_TOL,
            abs_tol_rad=VERIFY_ABS_TOL_PX / theta_k[0],
            min_agreement=VERIFY_MIN_AGREEMENT,
        )
        if best is None or np.count_nonzero(keep) > np.count_nonzero(best[2]):
            best = (theta_k, scale, keep)
    return best if best is not None else (np.array(theta, dtype=np.float64), 1.0, np.zeros(n, dtype=bool))


def _verify(
    x_px, y_px, r, theta, mirrored: bool, scale: float | None = None, prune: bool = False, r_corner_px: float = 0.0
) -> _Verified:
    """The project's own checks of candidate pairs (module docstring, steps 2 and 4) at one parity. ``scale``: the
    focal-length scale when already known (else estimated from the pairs, and k1 with it when the vote at it keeps
    under :data:`RADIAL_SEARCH_BELOW` of the candidates: :func:`_radial_search`); ``prune``: drop the least consistent
    candidates first (:data:`PRUNE_MIN_AGREEMENT`), for proposals with many wrong pairs. ``r_corner_px``: the
    detector's half-diagonal (:data:`REFINE_K2_SPAN`; 0: the farthest candidate's radius)."""
    n = x_px.shape[0]
    nothing = _Verified(np.zeros(n, dtype=bool), mirrored, math.nan, math.nan, None, None)
    if n < 3:
        return nothing
    data = build_data(_mirror_x(x_px, theta, mirrored), y_px, r, np.zeros(n, dtype=np.int64))
    table = pair_table(data)  # the catalogue side of the candidates' pairs, for the scale, the vote and the triples
    estimated = scale is None
    if scale is None:
        scale, n_pairs = estimate_scale_of_table(data, table, theta)
        if n_pairs == 0:
            return nothing
    theta_s = np.array(theta, dtype=np.float64)
    theta_s[0] *= scale
    b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    tolerances = {"rel_tol": VERIFY_REL_TOL, "abs_tol_rad": VERIFY_ABS_TOL_PX / theta_s[0]}
    alive = np.ones(n, dtype=bool)
    while prune and np.count_nonzero(alive) >= 3:
        sub = np.flatnonzero(alive)
        if sub.size == n:  # every candidate: the table's pairs
            ok = vote_of_table(table, b, n, min_agreement=PRUNE_MIN_AGREEMENT, **tolerances)
        else:
            part, _, _ = data.select(alive, min_stars=1)
            ok = vote_consistent_stars(part, b[sub], min_agreement=PRUNE_MIN_AGREEMENT, **tolerances)
        if np.all(ok):
            break
        alive[sub[~ok]] = False
    keep = np.zeros(n, dtype=bool)
    sub = np.flatnonzero(alive)
    if sub.size == n:  # every candidate: the table's pairs
        keep = vote_of_table(table, b, n, min_agreement=VERIFY_MIN_AGREEMENT, **tolerances)
        if estimated and n <= RADIAL_SEARCH_MAX_STARS and np.count_nonzero(keep) < RADIAL_SEARCH_BELOW * n:
            r_corner = r_corner_px or float(np.max(np.hypot(data.x_px - theta[1], data.y_px - theta[2])))
            searched = _radial_search(data, table, theta, r_corner)
            if np.count_nonzero(searched[2]) > np.count_nonzero(keep):
                theta_s, scale, keep = searched
                b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    elif sub.size >= 3:
        part, _, _ = data.select(alive, min_stars=1)
        keep[sub] = vote_consistent_stars(part, b[sub], min_agreement=VERIFY_MIN_AGREEMENT, **tolerances)
    if np.count_nonzero(keep) < 3:
        return _Verified(keep, mirrored, scale, math.nan, None, None)
    opposite, total = triple_handedness_of_table(table, b, keep)
    agreement = 1.0 - opposite / total if total else math.nan
    try:
        c = attitude_from_vectors(b[keep], r[keep])
    except DegenerateGeometry:
        return _Verified(keep, mirrored, scale, agreement, None, None)
    if np.count_nonzero(keep) >= REFINE_MIN_STARS:
        theta_0 = theta_s
        r_corner = r_corner_px or float(np.max(np.hypot(data.x_px - theta_s[1], data.y_px - theta_s[2])))
        theta_s, c = _refine_radial(data.x_px[keep], data.y_px[keep], r[keep], c, theta_0, r_corner)
        b = pixels_to_unit(data.x_px, data.y_px, theta_s)
        for _ in range(RESIDUAL_GATE_ROUNDS):
            misfit = keep & _residual_outliers(residuals_rad(b, r, c) * theta_s[0], keep)
            if not np.any(misfit) or np.count_nonzero(keep & ~misfit) < REFINE_MIN_STARS:
                break
            keep &= ~misfit  # refitted without them: a few wrong pairs far off pull a least-squares fit everywhere
            c = attitude_from_vectors(pixels_to_unit(data.x_px[keep], data.y_px[keep], theta_0), r[keep])
            theta_s, c = _refine_radial(data.x_px[keep], data.y_px[keep], r[keep], c, theta_0, r_corner)
            b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    return _Verified(keep, mirrored, scale, agreement, c, residuals_rad(b, r, c), theta_s)


def _absolute_scale(v: _Verified, theta: np.ndarray) -> float:
    """F / F_nominal of a verification (its camera vector's focal length over the nominal's ``theta``)."""
    return float(v.theta[0] / theta[0]) if v.theta is not None else v.scale


def _verify_best_parity(
    x_px, y_px, r, theta, mirrored_hint: bool, scale=None, prune=False, r_corner_px: float = 0.0
) -> _Verified:
    """Both parities, the hinted one first; the first whose triples agree wins."""
    first = _verify(x_px, y_px, r, theta, mirrored_hint, scale, prune, r_corner_px)
    if first.parity_agreement >= PARITY_MIN_AGREEMENT:
        return first
    second = _verify(x_px, y_px, r, theta, not mirrored_hint, scale, prune, r_corner_px)
    if second.parity_agreement >= PARITY_MIN_AGREEMENT:
        return second
    return first


def _scale_through(x_px, y_px, r, theta, mirrored: bool) -> float:
    """F / F of ``theta`` that the stars' pairs measure through it (:func:`estimate_scale_of_table`; NaN without a
    pair long enough)."""
    data = build_data(_mirror_x(x_px, theta, mirrored), y_px, r, np.zeros(x_px.shape[0], dtype=np.int64))
    scale, n_pairs = estimate_scale_of_table(data, pair_table(data), theta)
    return float(scale) if n_pairs else math.nan
