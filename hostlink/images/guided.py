"""Guided admission of faint candidates (issue 30): a candidate below the detection threshold (a session row with an
``snr``, written by ``hostlink centroid``, :func:`hostlink.images.centroid._candidates`) is named only where the
calibrated camera and the frame's attitude predict a catalogue star, after identification is over.

Identification never sees the candidates (:func:`identify_then_admit` holds them back: they build no pattern and
vote for none). Then, with the camera calibrated on the identified stars
(:func:`hostlink.calibration.run.calibrate_session`, default method) and per frame:

1. the attitude: Markley's SVD (:func:`onboard.attitude.attitude_from_vectors`) of the frame's identified stars
   (at least :data:`MIN_FRAME_STARS`) through the calibrated camera (the parity that fits: a mirrored detector is
   mirrored about the principal point), and the prediction's 1-sigma per axis sigma_pred [px]: the RMS residual of
   those stars per axis (it holds their own centroid noise too: an upper bound);
2. the photometric zero point: the median of catalogue magnitude less instrumental magnitude over the frame's
   identified unsaturated stars, and its scatter s (1.4826 x the median absolute deviation);
3. every catalogue star the attitude puts on the detector that the frame has not identified is searched for within
   r = :data:`CONTAINMENT_SIGMAS` x sqrt(sigma_pred^2 + sigma_px^2) of its predicted place (its blend's reference,
   with that reference's sigma added, when unresolved companions add their light: :func:`_blend_places`; sigma_px
   the row's own centroid noise, there less an elongated blend's bound ``blend_px`` the reference models: 99 % of
   the true positions fall inside, a 2-D Gaussian's 3.03 sigma) among the rows left
   unidentified: the candidates, and the detected stars identification did not name (its radius, before the
   camera was calibrated, was several pixels where this one is about one); a row there is admitted when its
   instrumental magnitude agrees with the star's predicted one within
   dm = max(:data:`PHOTOMETRIC_SIGMAS` x s, :data:`MIN_PHOTOMETRIC_WINDOW_MAG`), it is the only such row of that
   star, that star the only catalogue star that could be it (within r or :data:`UNRESOLVED_PX`, whichever is
   larger, and bright enough to explain its flux by itself, :func:`hostlink.images.blends.could_be`: a star two
   catalogue stars could be stays unidentified; a fainter companion's light is in the row, whose reference is then
   the pair's photocentre, :func:`hostlink.images.blends.blend_references`),
   and no other row of the frame is nearer to the prediction.

False admissions: the candidates are mostly noise, and noise peaks fall anywhere. Taking every unidentified row of
the frame whose magnitude would agree with a searched star as noise, spread uniformly over the detector (an upper
bound: real faint stars are among them), the expected number that falls within a searched star's radius by chance is
sum_j n_j pi r_j^2 / A (n_j those candidates, A the detector's area); it is computed and reported per frame
(``expected_false``) beside the number admitted, and checked on rendered frames with noise only at the searched
places (tests/test_images_guided.py). A frame where chance would explain more than :data:`MAX_FALSE_FRACTION` of its
admissions admits none (its record says so, with the figures).

Each admitted star keeps its ``sigma_px``: the calibration weights it by it, so a faint star counts little.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from hostlink.files.session import Session, session_filled, session_flag, session_number
from hostlink.images.blends import (
    MAD_TO_SIGMA,  # noqa: F401 - importable from here as before
    MIN_PHOTOMETRIC_WINDOW_MAG,  # noqa: F401
    PHOTOMETRIC_SIGMAS,  # noqa: F401
    UNRESOLVED_PX,
    blend_references,
    could_be,
    window_mag,
    without_pair_bound,
    zero_point,
)
from hostlink.images.extend import _near_pairs, _nearest_rows
from hostlink.images.skyindex import SkyIndex, _mirror_x, sky_index
from hostlink.sky.catalogue import Catalogue
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.camera import pixels_to_unit, unit_to_pixels
from onboard.params import CameraParams

#: The session column that marks a candidate (its significance; empty on detected stars).
SNR_COLUMN = "snr"
#: Radius in units of the combined 1-sigma per axis: a 2-D Gaussian puts 99 % of its mass within sqrt(-2 ln 0.01).
CONTAINMENT_SIGMAS = math.sqrt(-2.0 * math.log(0.01))
#: A frame's admissions stand only when noise would explain at most this fraction of them (the expected number by
#: chance over the number admitted): a wrong identity that reaches the fit is worse than none, and the calibration's
#: outlier rejection is built for a few percent.
MAX_FALSE_FRACTION = 0.05
#: A frame needs this many identified stars for its attitude and zero point (three for an attitude, more for a
#: residual that says how well it predicts).
MIN_FRAME_STARS = 6
#: Catalogue stars more than this far from the boresight [deg] are not projected: the pinhole model maps only
#: directions in front of the camera.
MAX_OFF_BORESIGHT_DEG = 89.0
#: The projected cone reaches 2 % beyond the undistorted field's half-diagonal in cos (2 deg beyond a 30-deg half-
#: diagonal, 7 deg beyond a 6-deg one): a barrel lens brings stars from outside that cone onto the detector, and the
#: projection itself then keeps only the stars that land on it.
FIELD_CONE_MARGIN = 0.98


@dataclass(frozen=True)
class FrameAdmission:
    """One frame's guided admission: catalogue stars searched, candidates admitted, the expected number of them that
    noise put there by chance, the prediction's 1-sigma per axis [px] and the zero point's scatter [mag]."""

    frame: int
    searched: int = 0
    admitted: int = 0
    expected_false: float = 0.0
    prediction_sigma_px: float = math.nan
    zero_point_scatter_mag: float = math.nan
    status: str = "admitted"


def candidate_rows(session: Session) -> np.ndarray:
    """(N,) bool: the rows that are candidates (an ``snr`` value), none when the session has no such column."""
    return session_filled(session, SNR_COLUMN)


def identify_without_candidates(session: Session, identify):
    """``identify(session)`` on the session without its candidates (they build no pattern), every row back in place
    (the candidates unidentified): what :func:`hostlink.images.identify.identify_session` sees of a session that
    holds candidates."""
    held = candidate_rows(session)
    stars = np.flatnonzero(~held)
    result = identify(session.select(stars))
    blends = tuple({**b, "row": int(stars[b["row"]])} for b in result.blends)  # rows of the whole session
    return replace(result, session=_merged(session, stars, result.session, session.star_id.copy()), blends=blends)


def _merged(session: Session, stars: np.ndarray, identified: Session, star_id: np.ndarray) -> Session:
    """``session`` with ``star_id``, the rows ``stars`` taking ``identified``'s identities, places (ra/dec: new
    columns when only ``identified`` has them, a blend's photocentre) and extra columns (a blend's ``sigma_px``)."""
    star_id[stars] = identified.star_id
    out = replace(session, star_id=star_id)
    if identified.ra_deg is not None and identified.dec_deg is not None:
        none = np.full(len(session), np.nan)
        ra = none.copy() if session.ra_deg is None else session.ra_deg.copy()
        dec = none.copy() if session.dec_deg is None else session.dec_deg.copy()
        ra[stars], dec[stars] = identified.ra_deg, identified.dec_deg
        out = replace(out, ra_deg=ra, dec_deg=dec)
    if session.extra:
        extra = {}
        for name, values in session.extra.items():
            extra[name] = values.copy()
            if name in identified.extra:
                extra[name][stars] = identified.extra[name]
        out = replace(out, extra=extra)
    return out


def identify_then_admit(session: Session, identify, catalogue: Catalogue | None = None, index: SkyIndex | None = None):
    """``identify(session)`` (an :class:`hostlink.images.identify.Identification`) on the session without its
    candidates, then the candidates admitted (module docstring) with the camera calibrated on what it identified.
    Returns the identification with every row back in place (candidates not admitted unidentified) and one more
    record in ``rounds``: ``{"round": "guided", ...}`` with the per-frame admissions. BLAS on one thread
    (:func:`hostlink.calibration.data.one_blas_thread`): the products here are thin (the catalogue's directions by
    an attitude, per-frame pairs). ``index``: the :class:`SkyIndex` of ``catalogue`` when the caller holds one."""
    from hostlink.calibration.data import one_blas_thread

    with one_blas_thread():
        return _identify_then_admit(session, identify, catalogue, index)


def _identify_then_admit(session: Session, identify, catalogue: Catalogue | None, index: SkyIndex | None):
    """:func:`identify_then_admit`."""
    held = candidate_rows(session)
    if not np.any(held):
        return identify(session)
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    index = sky_index(catalogue, index)
    stars = np.flatnonzero(~held)
    result = identify(session.select(stars))
    star_id = session.star_id.copy()
    star_id[stars] = result.session.star_id
    record = {
        "round": "guided",
        "camera": "calibrated on the identified stars",
        # the identification's camera until the calibration succeeds (a report holds no NaN: strict JSON)
        "focal_length_px": None if result.camera is None else float(result.camera.focal_length_px),
        "frames_identified": result.n_frames_identified,
        "stars_identified": result.n_identified,
        "added": 0,
        "lost": 0,
        "renamed": 0,
        "kept": True,
    }
    camera = _calibrated(result.session, result.camera, getattr(result, "calibration", None))
    if camera is None:
        record.update(
            camera="the identification's (calibration failed)", status="calibration failed: no candidate admitted"
        )
        frames = ()
    else:
        star_id, frames = admit(session, star_id, held, camera, catalogue, index)
        record.update(
            focal_length_px=float(camera.focal_length_px),
            status="admitted",
            added=int(sum(f.admitted for f in frames)),
            expected_false=float(sum(f.expected_false for f in frames if f.status == "admitted")),
            frames_declined=int(sum(f.status.startswith("not admitted") for f in frames)),
            max_false_fraction=MAX_FALSE_FRACTION,
            searched=int(sum(f.searched for f in frames)),
            # a frame that admits nothing has no prediction sigma or zero point: null, not NaN (strict JSON)
            per_frame=[{k: None if v != v else v for k, v in vars(f).items()} for f in frames],
        )
        record["stars_identified"] = result.n_identified + record["added"]
    from hostlink.images.skyindex import _with_identities  # the identified rows' places, as identify fills them

    # every row identified here, detected or admitted, with its unresolved companions' light (blends.py), at the
    # calibrated focal length
    focal_px = (camera or result.camera).focal_length_px
    identified = _with_identities(session, star_id, catalogue)
    out, blends = blend_references(identified, session.star_id, catalogue, focal_px, index)
    record["blends"] = len(blends)
    return replace(result, session=out, rounds=(*result.rounds, record), blends=tuple(blends))


def _calibrated(session: Session, camera: CameraParams | None, outcome=None) -> CameraParams | None:
    """The camera calibrated on ``session``'s identified stars (default method) from ``camera``, None when that
    fails. ``outcome``: that calibration when the identification's rounds already ran it
    (:attr:`hostlink.images.identify.Identification.calibration`), not run again."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.errors import UserError

    if camera is None or not np.any(session.star_id != 0):
        return None
    if outcome is None:
        try:
            outcome, _ = calibrate_session(session, camera, keep_failed=True, mirror_fit=False)
        except UserError:
            return None
    return None if outcome.failure() else outcome.params


def admit(
    session: Session,
    star_id: np.ndarray,
    held: np.ndarray,
    camera: CameraParams,
    catalogue: Catalogue,
    index: SkyIndex | None = None,
) -> tuple[np.ndarray, tuple[FrameAdmission, ...]]:
    """``star_id`` with the admitted candidates (rows ``held``) named, frame by frame (module docstring), and each
    frame's :class:`FrameAdmission`. ``index``: the :class:`SkyIndex` of ``catalogue`` (built here when not given)."""
    index = sky_index(catalogue, index)
    theta = camera.model_vector(np.float64)
    out = star_id.copy()
    frames = []
    saturated = session_flag(session, "saturated")
    sigma_px = session_number(session, "sigma_px")
    own_px = without_pair_bound(sigma_px, session_number(session, "blend_px"))  # at a blend's reference
    starts = session.frame_starts
    for k in range(session.n_frames):
        rows = np.arange(int(starts[k]), int(starts[k + 1]))
        names, record = _admit_frame(
            session.x_px[rows],
            session.y_px[rows],
            session.mag[rows] if session.mag is not None else np.full(rows.size, np.nan),
            out[rows],
            held[rows],
            saturated[rows],
            (sigma_px[rows], own_px[rows]),
            theta,
            camera.image_size_px,
            index,
            catalogue,
        )
        out[rows] = names
        frames.append(replace(record, frame=int(session.frame[rows[0]]) if rows.size else k))
    return out, tuple(frames)


def _admit_frame(x, y, mag, star_id, held, saturated, sigma_px, theta, image_size_px, index, catalogue):
    """One frame of :func:`admit`: (its star ids with the admitted candidates named, its :class:`FrameAdmission`).
    ``sigma_px``: the rows' ``sigma_px`` and that without an elongated blend's bound (``blend_px``, which a blend's
    reference replaces: :func:`hostlink.images.blends.without_pair_bound`)."""
    sigma_px, own_px = sigma_px
    named = (star_id != 0) & ~held
    if np.count_nonzero(named) < MIN_FRAME_STARS:
        return star_id, FrameAdmission(0, status=f"fewer than {MIN_FRAME_STARS} identified stars")
    cat_rows = np.searchsorted(catalogue.hip, star_id[named])
    fit = _frame_attitude(x[named], y[named], index.directions[cat_rows], theta)
    if fit is None:
        return star_id, FrameAdmission(0, status="no attitude")
    c, mirrored, sigma_pred = fit
    bright = named & ~saturated & np.isfinite(mag)
    if np.count_nonzero(bright) < MIN_FRAME_STARS:
        return star_id, FrameAdmission(0, status=f"fewer than {MIN_FRAME_STARS} unsaturated identified stars")
    zp, scatter = zero_point(catalogue.mag[np.searchsorted(catalogue.hip, star_id[bright])], mag[bright])
    window = window_mag(scatter)
    near, xp, yp = _predicted(index.directions, c, theta, mirrored, image_size_px)
    searched = ~np.isin(catalogue.hip[near], star_id[named])
    near, xp, yp = near[searched], xp[searched], yp[searched]
    # a star whose unresolved companions add their light is expected at its blend's centroid (blends.py)
    xp, yp, sigma_ref = _blend_places(near, xp, yp, index, (c, theta, mirrored), catalogue, star_id[named], scatter)
    predicted_mag = catalogue.mag[near] - zp  # instrumental
    # every row left unidentified: the candidates, and the detected stars identification could not name (with the
    # calibrated camera the radius is a pixel or less, where the uncalibrated one needed several)
    cand = np.flatnonzero((star_id == 0) & np.isfinite(mag) & np.isfinite(sigma_px) & (sigma_px > 0))
    rows, stars = _admissions(
        (x, y, mag, sigma_px, own_px), cand, (xp, yp, predicted_mag, sigma_ref), sigma_pred, window
    )
    names = star_id.copy()
    names[rows] = catalogue.hip[near[stars]]
    admitted = int(rows.size)
    # chance: every candidate whose magnitude agrees with star j, spread over the detector, falling within r of it
    # (per candidate and star: the prediction's, the row's and the blend reference's 1-sigma combined)
    width, height = image_size_px
    expected = _chance_expected(
        (mag[cand], sigma_px[cand], own_px[cand]), (predicted_mag, sigma_ref), sigma_pred, window, width * height
    )
    record = FrameAdmission(0, int(near.size), admitted, expected, sigma_pred, scatter)
    if expected > MAX_FALSE_FRACTION * admitted:
        return star_id, replace(record, admitted=0, status="not admitted: chance too high")
    return names, record


#: Candidate-star pairs of :func:`_chance_expected` formed at once (~32 MB per float64 array): a 24 Mpx frame has
#: ~10^4 candidates and thousands of predicted stars (6610 Hipparcos stars in the 55-deg render's field), ~5 x 10^7
#: pairs, over a GB in the matrix's float64 arrays (docs/realsky.md "Large frames").
CHANCE_BLOCK_PAIRS = 4_000_000


def _chance_expected(cands, stars, sigma_pred: float, window: float, area_px: float) -> float:
    """The admissions chance explains in one frame: every candidate whose magnitude agrees with star j (within
    ``window``), spread uniformly over the detector of ``area_px`` pixels, falls within r of it with probability
    pi r^2 / area (r per candidate and star: the prediction's, the row's and the blend reference's 1-sigma combined,
    x :data:`CONTAINMENT_SIGMAS`), summed over all pairs. ``cands`` = (mag, sigma_px, own_px) of the candidates,
    ``stars`` = (predicted instrumental mag, sigma_ref) of the searched stars. Summed over blocks of candidates of
    at most :data:`CHANCE_BLOCK_PAIRS` pairs, so memory is bounded whatever the counts (one block: the sum of one
    matrix, as before the blocks)."""
    mag, sigma_px, own_px = cands
    predicted_mag, sigma_ref = stars
    step = max(1, CHANCE_BLOCK_PAIRS // max(predicted_mag.size, 1))
    total = 0.0
    for k in range(0, mag.size, step):
        part = slice(k, k + step)
        row_px = _row_sigma_px(sigma_px[part, None], own_px[part, None], sigma_ref[None, :])
        radius = CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + row_px**2 + sigma_ref[None, :] ** 2)
        agree = np.abs(mag[part, None] - predicted_mag[None, :]) <= window
        total += np.sum(agree * (math.pi * radius**2))
    return float(total / area_px)


def _admissions(rows, cand, predictions, sigma_pred: float, window: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidates admitted in one frame (module docstring) and the predicted stars they are: (frame rows, indices
    into the predictions). ``rows`` = (x, y, mag, sigma_px) of every row of the frame, ``cand`` the rows that may be
    named (``own_px``: sigma_px without an elongated blend's bound), ``predictions`` = (xp, yp, predicted
    instrumental mag, sigma_ref) of the searched catalogue stars.

    Candidate i could be star j when near enough (within r = :data:`CONTAINMENT_SIGMAS` x the prediction's, the
    row's and the blend reference's 1-sigma combined) and as bright as predicted (within ``window``); every star
    that could be the row by itself (within r or :data:`UNRESOLVED_PX`, bright enough to explain its flux: a fainter
    one is a companion whose light is in the row, hostlink.images.blends) is its rival. A row is admitted when it
    could be one star only, has no other rival, no other row could be that star, and it is the frame's row nearest
    to that star's prediction (an identified star nearer to it is that star's). Only the pairs within the largest
    of these radii are formed (:func:`_near_pairs`): the others are neither near nor rivals."""
    x, y, mag, sigma_px, own_px = rows
    xp, yp, predicted_mag, sigma_ref = predictions
    none = np.zeros(0, dtype=np.int64)
    if cand.size == 0 or xp.size == 0:
        return none, none
    # the largest r (the same operations as each pair's, on the largest terms: rounding is monotonic)
    reach_px = max(
        float(CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + np.max(sigma_px[cand] ** 2) + np.max(sigma_ref**2))),
        UNRESOLVED_PX,
    )
    row, star, d2 = _near_pairs(x, y, xp, yp, reach_px)
    nearest = _nearest_rows(row, star, d2, xp.size)
    of_cand = np.full(x.size, -1, dtype=np.int64)
    of_cand[cand] = np.arange(cand.size)
    pair = of_cand[row] >= 0
    i, j, d2 = of_cand[row[pair]], star[pair], d2[pair]
    row_px = _row_sigma_px(sigma_px[cand[i]], own_px[cand[i]], sigma_ref[j])
    r = CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + row_px**2 + sigma_ref[j] ** 2)
    agree = np.abs(mag[cand[i]] - predicted_mag[j]) <= window
    rival = (d2 <= np.maximum(r, UNRESOLVED_PX) ** 2) & could_be(predicted_mag[j], mag[cand[i]], window)
    match = (d2 <= r**2) & agree
    rivals_of_row = np.bincount(i[rival], minlength=cand.size)
    i, j = i[match], j[match]
    matches_of_row = np.bincount(i, minlength=cand.size)
    matches_of_star = np.bincount(j, minlength=xp.size)
    ok = (matches_of_row[i] == 1) & (rivals_of_row[i] == 1) & (matches_of_star[j] == 1) & (nearest[j] == cand[i])
    return cand[i[ok]], j[ok]


def _row_sigma_px(sigma_px: np.ndarray, own_px: np.ndarray, sigma_ref: np.ndarray) -> np.ndarray:
    """A row's 1-sigma against a prediction: without an elongated blend's bound where the prediction is a blend's
    reference (``sigma_ref`` > 0: the reference models that shift, so the bound is counted once), else as written."""
    return np.where(sigma_ref > 0, own_px, sigma_px)


def _blend_places(near, xp, yp, index, view, catalogue: Catalogue, named_hip: np.ndarray, scatter: float):
    """(xp, yp, sigma_ref [px]) of the searched catalogue stars ``near`` (their single-star places ``xp, yp``): where
    a star has catalogue companions within :data:`UNRESOLVED_PX` that the frame has not identified as rows of their
    own (``named_hip``), its expected place is its blend's reference (:func:`hostlink.images.blends.photocentre`)
    through the attitude and camera ``view`` = (C, theta, mirrored), with that reference's 1-sigma; 0 elsewhere."""
    from hostlink.images.blends import photocentre

    c, theta, mirrored = view
    xp, yp, sigma_ref = xp.copy(), yp.copy(), np.zeros(near.size)
    directions = index.directions
    found = index.tree.query_ball_point(directions[near], 2.0 * math.sin(0.5 * UNRESOLVED_PX / float(theta[0])))
    for k, (j, close) in enumerate(zip(near, found, strict=True)):
        companions = [i for i in close if i != j and catalogue.hip[i] not in named_hip] if len(close) > 1 else []
        if not companions:
            continue
        pc = photocentre(
            directions[j],
            float(catalogue.mag[j]),
            directions[companions],
            catalogue.mag[companions],
            float(theta[0]),
            scatter,
        )
        u, v = unit_to_pixels((c @ pc.direction)[None, :], theta)
        xp[k], yp[k], sigma_ref[k] = _mirror_x(u[0], theta, mirrored), v[0], pc.sigma_px
    return xp, yp, sigma_ref


def _frame_attitude(x, y, r, theta):
    """(C, mirrored, sigma_pred [px per axis]) of the frame's identified stars through the camera ``theta`` at the
    parity that fits better (None when degenerate)."""
    best = None
    for mirrored in (False, True):
        b = pixels_to_unit(_mirror_x(x, theta, mirrored), y, theta)
        try:
            c = attitude_from_vectors(b, r)
        except DegenerateGeometry:
            continue
        rms_rad = float(np.sqrt(np.mean(residuals_rad(b, r, c) ** 2)))
        if best is None or rms_rad < best[2]:
            best = (c, mirrored, rms_rad)
    if best is None:
        return None
    c, mirrored, rms_rad = best
    return c, mirrored, rms_rad * float(theta[0]) / math.sqrt(2.0)


def _predicted(directions, c, theta, mirrored: bool, image_size_px):
    """(catalogue rows, x, y [px]) of the catalogue stars the attitude ``c`` puts on the detector."""
    width, height = image_size_px
    b = directions @ c.T
    front = np.flatnonzero(b[:, 2] > math.cos(math.radians(MAX_OFF_BORESIGHT_DEG)))
    half_diagonal = math.hypot(width, height) / (2.0 * theta[0])
    front = front[b[front, 2] >= math.cos(math.atan(half_diagonal)) * FIELD_CONE_MARGIN]
    if front.size == 0:
        return front, np.zeros(0), np.zeros(0)
    try:
        xp, yp = unit_to_pixels(b[front], theta)
    except ValueError:
        return front[:0], np.zeros(0), np.zeros(0)
    xp = _mirror_x(xp, theta, mirrored)
    on = (xp >= -0.5) & (xp <= width - 0.5) & (yp >= -0.5) & (yp <= height - 0.5)
    return front[on], xp[on], yp[on]
