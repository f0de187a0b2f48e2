"""Extension of a verified proposal (:mod:`hostlink.images.identify`, module docstring step 3): the catalogue stars the
verified attitude and camera put on the detector (:func:`_predict`), the centroids matched to them (:func:`_extend`),
the stars two catalogue stars could be (:func:`_ambiguous`, photometry by :mod:`hostlink.images.blends`), the
completeness of a solution (:func:`_completeness`) and the photometric check of a candidate (:func:`_too_faint`)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hostlink.images import blends
from hostlink.images.skyindex import _mirror_x, _Sky
from hostlink.images.verify import (
    _K1,
    RADIAL_SEARCH_BELOW,
    RADIAL_SEARCH_CORNER,
    _scale_through,
    _Verified,
)
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.camera import pixels_to_unit, unit_to_pixels

#: Extension: a centroid within this many rms residuals of the verified stars (or :data:`EXTEND_RADIUS_PX`,
#: whichever is larger) of a predicted catalogue star is a candidate; the nearest other predicted star must be at
#: least twice as far. The radius follows the camera model's error: several px for an uncalibrated wide lens, about
#: a pixel once calibrated, where a fixed 4 px let false stars meet faint catalogue stars by chance (a 50-deg
#: field holds ~0.5 Hp <= 7.5 stars per square degree: 4 px of 0.94' is a 7 % chance per false star, 1.5 px 1 %).
EXTEND_RADIUS_RESIDUALS = 4.0
#: ... or this radius [px], whichever is larger (above).
EXTEND_RADIUS_PX = 1.5


#: Extension: catalogue stars down to this many magnitudes fainter than the faintest proposed match are predicted.
EXTEND_MAG_MARGIN = 1.0


def _predict(
    sky: _Sky, theta: np.ndarray, v: _Verified, image_size_px: tuple[int, int], mag_limit: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Catalogue stars at least ``mag_limit`` bright that the verified attitude and scale put on the detector:
    (sky indices, x [px], y [px]) in the detector's own columns (mirrored back for a mirrored detector)."""
    none = np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    theta_s = np.array(theta, dtype=np.float64)
    theta_s[0] *= v.scale
    if v.theta is not None:
        theta_s = v.theta
    width, height = image_size_px
    corners_x = np.array([-0.5, width - 0.5, -0.5, width - 0.5])
    corners_y = np.array([-0.5, -0.5, height - 0.5, height - 0.5])
    cos_field = float(np.min(pixels_to_unit(corners_x, corners_y, theta_s)[:, 2]))
    near = np.flatnonzero((sky.r @ v.attitude[2] >= cos_field - 1e-6) & (sky.mag <= mag_limit))  # row 3 of C: bore
    b_pred = sky.r[near] @ v.attitude.T
    front = b_pred[:, 2] > 0
    near, b_pred = near[front], b_pred[front]
    if near.size == 0:
        return none
    try:
        xp, yp = unit_to_pixels(b_pred, theta_s)
    except ValueError:
        return none
    xp = _mirror_x(xp, theta_s, v.mirrored)  # back to the detector's own columns
    on = (xp >= -0.5) & (xp <= width - 0.5) & (yp >= -0.5) & (yp <= height - 0.5)
    return near[on], xp[on], yp[on]


def _extend(
    x_px: np.ndarray,
    y_px: np.ndarray,
    sky: _Sky,
    theta: np.ndarray,
    v: _Verified,
    taken_rows: np.ndarray,
    mag_limit: float,
    image_size_px: tuple[int, int],
    calibrated_mag: np.ndarray | None = None,
    window: float = blends.MIN_PHOTOMETRIC_WINDOW_MAG,
) -> tuple[np.ndarray, np.ndarray]:
    """Candidates beyond the proposal's (module docstring, step 3): (rows into the frame, sky indices). With the
    centroids' calibrated magnitudes ``calibrated_mag`` (instrumental plus the frame's zero point), a centroid with
    several catalogue stars nearly as close (within twice the nearest's distance) is named after the one of them
    whose light alone can explain its flux (:func:`hostlink.images.blends.could_be` within ``window``) when only one
    can: a fainter star beside it adds light to it but cannot be it."""
    none = np.zeros(0, np.int64), np.zeros(0, np.int64)
    near, xp, yp = _predict(sky, theta, v, image_size_px, mag_limit)
    free = np.flatnonzero(~taken_rows)
    if near.size == 0 or free.size == 0:
        return none
    radius = _match_radius_px(theta, v)
    # Only a free centroid whose nearest predicted star lies within the radius can match, and the stars tied with
    # that nearest (closer than twice its distance) then lie within twice the radius: the (centroid, predicted star)
    # pairs that close (:func:`_near_pairs`), with their squared distances as a full (centroids, predicted) table
    # would hold them, give every test of that table (the same nearest, ties broken by the lower index).
    i, p, d2 = _near_pairs(x_px[free], y_px[free], xp, yp, 2.0 * radius)
    nearest = np.full(free.size, np.inf)
    np.minimum.at(nearest, i, d2)
    j = _nearest_rows(p, i, d2, free.size)  # each free centroid's nearest predicted star (-1: none within reach)
    tied = (d2 < 4.0 * nearest[i]) | (p == j[i])  # the other catalogue stars nearly as close ...
    ok = np.bincount(i[tied], minlength=free.size) == 1  # ... make it ambiguous
    if calibrated_mag is not None:  # ... unless the light of one alone can explain the centroid's flux
        known = np.isfinite(calibrated_mag[free])
        able = tied & blends.could_be(sky.mag[near][p], calibrated_mag[free][i], window)
        single = known & (np.bincount(i[able], minlength=free.size) == 1)
        j_able = j.copy()
        j_able[i[able]] = p[able]  # the one able star where there is one
        j = np.where(single, j_able, j)
        ok |= single
    ok &= np.isfinite(nearest)
    rows = np.flatnonzero(ok)
    jj = j[rows]
    ok[rows] = (x_px[free[rows]] - xp[jj]) ** 2 + (y_px[free[rows]] - yp[jj]) ** 2 <= radius * radius
    rows = np.flatnonzero(ok)
    at, star, star_d2 = _near_pairs(x_px, y_px, xp[j[rows]], yp[j[rows]], radius)
    ok[rows] = _nearest_rows(at, star, star_d2, rows.size) == free[rows]  # no other centroid nearer to the star
    return free[ok].astype(np.int64), near[j[ok]].astype(np.int64)


#: :func:`_near_pairs` searches a band of columns this much wider than the reach (relative, and as many pixels): no
#: rounding of the band's edges can then drop a pair within reach.
_BAND_SLACK = 1e-9


def _near_pairs(x, y, xp, yp, reach_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (row, prediction) pair of points (x, y) and (xp, yp) at most ``reach_px`` apart, with its squared
    distance (x - xp)^2 + (y - yp)^2 [px^2], the same numbers the full (rows x predictions) matrix holds: the
    predictions sorted by column, each row's run of predictions within a band of columns (:data:`_BAND_SLACK`) found
    by bisection, then each pair's distance tested. The extension, its ambiguity test and the guided admission
    (:mod:`hostlink.images.guided`) take their pairs here."""
    order = np.argsort(xp, kind="stable")
    sorted_xp = xp[order]
    band_px = reach_px * (1.0 + _BAND_SLACK) + _BAND_SLACK
    lo = np.searchsorted(sorted_xp, x - band_px, side="left")
    counts = np.searchsorted(sorted_xp, x + band_px, side="right") - lo
    row = np.repeat(np.arange(x.size), counts)
    # the k-th pair of a row's run is its prediction lo + (k - the run's first pair)
    star = order[np.repeat(lo - (np.cumsum(counts) - counts), counts) + np.arange(row.size)]
    d2 = (x[row] - xp[star]) ** 2 + (y[row] - yp[star]) ** 2
    keep = d2 <= reach_px * reach_px
    return row[keep], star[keep], d2[keep]


def _nearest_rows(row: np.ndarray, star: np.ndarray, d2: np.ndarray, n_stars: int) -> np.ndarray:
    """Per prediction, the row nearest to it among the pairs of :func:`_near_pairs` (-1 when none is within reach),
    the lower row on a tie: the frame's nearest row wherever one is within reach, as ``argmin`` over every row.
    (Called with ``row`` and ``star`` swapped: per row, the nearest prediction.)"""
    nearest = np.full(n_stars, -1, dtype=np.int64)
    order = np.lexsort((row, d2, star))
    first = np.ones(order.size, dtype=bool)
    first[1:] = star[order][1:] != star[order][:-1]
    nearest[star[order][first]] = row[order][first]
    return nearest


def _match_radius_px(theta: np.ndarray, v: _Verified) -> float:
    """The radius [px] within which a centroid is matched to a predicted catalogue star: :data:`EXTEND_RADIUS_PX`,
    or :data:`EXTEND_RADIUS_RESIDUALS` x the verified stars' rms residual when larger."""
    focal_px = v.theta[0] if v.theta is not None else theta[0] * v.scale
    rms_px = float(np.sqrt(np.mean(v.residual_rad[v.keep] ** 2))) * focal_px
    return max(EXTEND_RADIUS_PX, EXTEND_RADIUS_RESIDUALS * rms_px)


#: A star is ambiguous when another catalogue star at most this much fainter than its own identity [mag] is
#: predicted within the match radius of its centroid (the depth the extension matches to, :data:`EXTEND_MAG_MARGIN`).
AMBIGUITY_MAG_MARGIN = EXTEND_MAG_MARGIN


def _ambiguous(
    x_px: np.ndarray,
    y_px: np.ndarray,
    stars: np.ndarray,
    sky: _Sky,
    theta: np.ndarray,
    v: _Verified,
    image_size_px: tuple[int, int],
    mag_limit: float,
    detection_mag: np.ndarray | None = None,
    window: float = blends.MIN_PHOTOMETRIC_WINDOW_MAG,
) -> np.ndarray:
    """(K,) bool over the candidates (centroids ``x_px, y_px`` named ``stars``): another catalogue star within
    ``mag_limit`` that could be this centroid is predicted by the verified solution within :func:`_match_radius_px`
    of it: two catalogue stars could be this star (a close pair the detector does not resolve, or either of two), so
    it is left unidentified. "Could be": with the centroids' calibrated magnitudes ``detection_mag`` (instrumental
    plus the frame's zero point) bright enough to explain the measured flux by itself within the photometric
    ``window`` (:func:`hostlink.images.blends.could_be`: a fainter companion only adds its light, and the centroid is
    its identity or the blend); where that magnitude is unknown, no fainter than the identity by more than
    :data:`AMBIGUITY_MAG_MARGIN`."""
    near, xp, yp = _predict(sky, theta, v, image_size_px, mag_limit)
    out = np.zeros(stars.size, dtype=bool)
    if near.size < 2:
        return out
    radius = _match_radius_px(theta, v)
    # the (candidate, predicted star) pairs within the radius (their squared distances as a full table holds them)
    i, p, d2 = _near_pairs(x_px, y_px, xp, yp, radius)
    other = (d2 <= radius * radius) & (near[p] != stars[i])
    bright_enough = sky.mag[near][p] <= sky.mag[stars][i] + AMBIGUITY_MAG_MARGIN
    if detection_mag is not None:
        known = np.isfinite(detection_mag)
        explains = blends.could_be(sky.mag[near][p], detection_mag[i], window)
        bright_enough = np.where(known[i], explains, bright_enough)
    out[np.unique(i[other & bright_enough])] = True
    return out


#: Completeness is counted only in the cells of a COMPLETENESS_CELLS x COMPLETENESS_CELLS grid over the detector that
#: hold at least one centroid: a part of the frame with no detection at all (a horizon, trees, a cloud bank) says
#: nothing about whether the solution is right (the rendered wide set's frames with a quarter of trees fell to 34-37 %).
COMPLETENESS_CELLS = 8


def _completeness(
    sky: _Sky,
    theta: np.ndarray,
    v: _Verified,
    image_size_px,
    identified: np.ndarray,
    x_px: np.ndarray | None = None,
    y_px: np.ndarray | None = None,
) -> float:
    """Of the catalogue stars the solution puts on the detector that are at least as bright as the median
    identified star, the fraction identified (a true solution finds most of them; a chance alignment of faint
    stars in a rich field leaves the bright ones of that field unmatched); with the frame's centroids ``x_px, y_px``,
    only in the cells where the frame has any (:data:`COMPLETENESS_CELLS`)."""
    mags = sky.mag[identified]
    near, xp, yp = _predict(sky, theta, v, image_size_px, float(np.median(mags)))
    if x_px is not None and near.size:
        width, height = image_size_px

        def cell(x, y):
            cx = np.clip((np.asarray(x) + 0.5) * COMPLETENESS_CELLS // width, 0, COMPLETENESS_CELLS - 1)
            cy = np.clip((np.asarray(y) + 0.5) * COMPLETENESS_CELLS // height, 0, COMPLETENESS_CELLS - 1)
            return (cy * COMPLETENESS_CELLS + cx).astype(np.int64)

        occupied = np.zeros(COMPLETENESS_CELLS * COMPLETENESS_CELLS, dtype=bool)
        occupied[cell(x_px, y_px)] = True
        near = near[occupied[cell(xp, yp)]]
    if near.size == 0:
        return 1.0
    return float(np.count_nonzero(np.isin(near, identified))) / near.size


#: Photometric check: a candidate whose catalogue star is more than this much fainter [mag] than its centroid's
#: brightness implies (the frame's zero point: the median of catalogue minus instrumental magnitude over its verified
#: stars) is not that star: a bright uncatalogued point (a planet, an aircraft, a hot pixel) or a wide lens's edge
#: star, misplaced by the distortion the frame has not yet measured, must not take the name of a faint catalogue star
#: that happens to lie near it. One-sided: clouds, vignetting, extinction and saturation make a star look fainter
#: than its catalogue magnitude, never brighter; only the camera's band against Hp (a red star in a red-sensitive
#: camera) and noise do. Measured: correct names lie at most 1.7 mag on that side on granasat (colour JPEG), 0.8 on
#: the rendered wide set (benchmarks/bench_widefield.py), whose wrong names of round 1 lay 2.5-4.5 mag beyond.
PHOTOMETRIC_TOL_MAG = 2.5


def _zero_point(mag: np.ndarray | None, rows: np.ndarray, stars: np.ndarray, sky: _Sky) -> float:
    """The frame's photometric zero point [mag]: the median of catalogue minus instrumental magnitude over the
    stars ``rows`` named ``stars`` (NaN without magnitudes; :func:`hostlink.images.blends.zero_point`)."""
    if mag is None:
        return math.nan
    return blends.zero_point(sky.mag[stars], mag[rows])[0]


def _too_faint(mag: np.ndarray | None, rows: np.ndarray, stars: np.ndarray, sky: _Sky, zero_point: float) -> np.ndarray:
    """(K,) bool: the candidates whose catalogue star is more than :data:`PHOTOMETRIC_TOL_MAG` fainter than their
    centroid's instrumental magnitude plus ``zero_point`` implies (False where either is unknown)."""
    if mag is None or not math.isfinite(zero_point):
        return np.zeros(rows.size, dtype=bool)
    with np.errstate(invalid="ignore"):
        return sky.mag[stars] > mag[rows] + zero_point + PHOTOMETRIC_TOL_MAG


def _calibrated_mag(
    mag: np.ndarray | None, at: np.ndarray, rows: np.ndarray, stars: np.ndarray, v: _Verified, sky: _Sky
) -> tuple[np.ndarray | None, float]:
    """(the calibrated magnitudes of the centroids ``at``: instrumental plus the frame's zero point over its verified
    stars (``rows`` named ``stars`` where ``v.keep``), the photometric window of that zero point's scatter) for
    :func:`_extend` and :func:`_ambiguous` ((None, window) without magnitudes)."""
    if mag is None:
        return None, blends.MIN_PHOTOMETRIC_WINDOW_MAG
    zp, scatter = blends.zero_point(sky.mag[stars[v.keep]], mag[rows[v.keep]])
    return mag[at] + zp, blends.window_mag(scatter)


def _faintest_detectable(mag: np.ndarray | None, zero_point: float) -> float:
    """The faintest catalogue magnitude a candidate of the frame may have (:func:`_too_faint` of its faintest
    centroid); +inf when unknown."""
    if mag is None or not math.isfinite(zero_point) or not np.any(np.isfinite(mag)):
        return math.inf
    return float(np.nanmax(mag)) + zero_point + PHOTOMETRIC_TOL_MAG


#: :func:`_radial_search_by_hits`: a predicted catalogue star is hit when a centroid lies within this radius [px]
#: (the verification's absolute tolerance: centroid noise plus the distortion a k1 alone leaves of a wider lens).
HIT_SEARCH_RADIUS_PX = 3.0


def _hit_fraction(x_px, y_px, sky, v, image_size_px, mag_limit) -> float:
    """The fraction of the catalogue stars to ``mag_limit`` that ``v`` puts on the detector with a centroid within
    :data:`HIT_SEARCH_RADIUS_PX` (0 when none is predicted)."""
    _, xp, yp = _predict(sky, v.theta, v, image_size_px, mag_limit)
    _, p, _ = _near_pairs(x_px, y_px, xp, yp, HIT_SEARCH_RADIUS_PX)
    return np.unique(p).size / xp.size if xp.size else 0.0


def _radial_search_by_hits(x_px, y_px, rows, stars, v, sky, image_size_px, mag_limit, rescale: bool) -> _Verified:
    """The own matcher's verified proposal (``rows``, ``stars``, ``v``: a few bright stars, which every k1 verifies
    alike) with k1 searched over the frame instead (:data:`RADIAL_SEARCH_CORNER`), when at its camera fewer than
    :data:`RADIAL_SEARCH_BELOW` of the catalogue stars to ``mag_limit`` it puts on the detector land on a centroid:
    for each k1 (and, with ``rescale``, the scale re-estimated through it from the proposal's pairs: a scan's step
    is the nominal's scale where the anchors lie, not a focal length) the attitude refitted on the proposal and the
    fraction of predicted stars hit counted; the most win (ties: the smallest |k1|), adopted only when at least
    :data:`RADIAL_SEARCH_BELOW` of them are hit (a lens that explains the field: a wrong proposal's chance hits stay
    near the centroids' density, a few %). The given ``v`` otherwise (docs/realsky.md, "Verification under a strong
    unknown lens")."""
    keep = v.keep
    xs, ys, rs = x_px[rows[keep]], y_px[rows[keep]], sky.r[stars[keep]]
    r_corner = 0.5 * math.hypot(*image_size_px)
    if _hit_fraction(x_px, y_px, sky, v, image_size_px, mag_limit) >= RADIAL_SEARCH_BELOW:
        return v
    best, best_hits = v, RADIAL_SEARCH_BELOW
    for corner in sorted(RADIAL_SEARCH_CORNER, key=abs):
        theta_k = np.array(v.theta, dtype=np.float64)
        theta_k[_K1] += corner / r_corner**2
        if rescale:
            scale = _scale_through(xs, ys, rs, theta_k, v.mirrored)
            if not math.isfinite(scale):
                continue
            theta_k[0] *= scale
        b = pixels_to_unit(_mirror_x(xs, theta_k, v.mirrored), ys, theta_k)
        try:
            c = attitude_from_vectors(b, rs)
        except DegenerateGeometry:
            continue
        trial = _Verified(keep, v.mirrored, v.scale, v.parity_agreement, c, None, theta_k)
        n_hits = _hit_fraction(x_px, y_px, sky, trial, image_size_px, mag_limit)
        if n_hits > best_hits or (n_hits == best_hits and best is v):
            b_all = pixels_to_unit(_mirror_x(x_px[rows], theta_k, v.mirrored), y_px[rows], theta_k)
            best, best_hits = replace(trial, residual_rad=residuals_rad(b_all, sky.r[stars], c)), n_hits
    return best
