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
   r = :data:`CONTAINMENT_SIGMAS` x sqrt(sigma_pred^2 + sigma_px^2) of its predicted place (sigma_px the row's own
   centroid noise: 99 % of the true positions fall inside, a 2-D Gaussian's 3.03 sigma) among the rows left
   unidentified: the candidates, and the detected stars identification did not name (its radius, before the
   camera was calibrated, was several pixels where this one is about one); a row there is admitted when its
   instrumental magnitude agrees with the star's predicted one within
   dm = max(:data:`PHOTOMETRIC_SIGMAS` x s, :data:`MIN_PHOTOMETRIC_WINDOW_MAG`), it is the only such row of that
   star, that star the only catalogue star that could be in it (within r or :data:`UNRESOLVED_PX`, whichever is
   larger, and no fainter than the row's magnitude + :data:`COMPANION_MAG`: a star two catalogue stars could be
   stays unidentified),
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

from hostlink.files.session import Session
from hostlink.sky.catalogue import Catalogue
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.camera import pixels_to_unit, radec_to_unit, unit_to_pixels
from onboard.params import CameraParams

#: The session column that marks a candidate (its significance; empty on detected stars).
SNR_COLUMN = "snr"
#: Radius in units of the combined 1-sigma per axis: a 2-D Gaussian puts 99 % of its mass within sqrt(-2 ln 0.01).
CONTAINMENT_SIGMAS = math.sqrt(-2.0 * math.log(0.01))
#: Photometric agreement: within this many of the frame's zero-point scatters ...
PHOTOMETRIC_SIGMAS = 3.0
#: ... and never narrower than this [mag] (a zero point from few stars; Hipparcos Hp against an unfiltered detector's
#: band differs by colour, a few tenths of a magnitude).
MIN_PHOTOMETRIC_WINDOW_MAG = 0.75
#: Two stars nearer than this [px] are one detection: the sum of two equal Gaussians of sigma s has a single peak
#: below a separation of 2 s, and 3 px is 2 s for PSFs up to 1.5 px (0.8-1.2 px on the granasat frames but the
#: trailed 30 s one, 0.77 px on a sharp 35 mm lens). A second catalogue star within it makes a row ambiguous (close
#: doubles: 16 Cyg A and B, 40" apart, are half a pixel at 78" per pixel).
UNRESOLVED_PX = 3.0
#: ... when it is at most this much fainter than the row [mag]: 10 % of the light, which moves a blend's centroid by
#: 10 % of the pair's separation (0.3 px at 3 px).
COMPANION_MAG = 2.5
#: A frame's admissions stand only when noise would explain at most this fraction of them (the expected number by
#: chance over the number admitted): a wrong identity that reaches the fit is worse than none, and the calibration's
#: outlier rejection is built for a few percent.
MAX_FALSE_FRACTION = 0.05
#: A frame needs this many identified stars for its attitude and zero point (three for an attitude, more for a
#: residual that says how well it predicts).
MIN_FRAME_STARS = 6
#: The normal distribution's sigma over its median absolute deviation (a robust scatter of the zero point).
MAD_TO_SIGMA = 1.4826
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
    values = session.extra.get(SNR_COLUMN) if session.extra else None
    if values is None:
        return np.zeros(len(session), dtype=bool)
    return np.array([str(v).strip().lower() not in ("", "nan") for v in values], dtype=bool)


def identify_without_candidates(session: Session, identify):
    """``identify(session)`` on the session without its candidates (they build no pattern), every row back in place
    (the candidates unidentified): what :func:`hostlink.images.identify.identify_session` sees of a session that
    holds candidates."""
    held = candidate_rows(session)
    stars = np.flatnonzero(~held)
    result = identify(session.select(stars))
    return replace(result, session=_merged(session, stars, result.session, session.star_id.copy()))


def _merged(session: Session, stars: np.ndarray, identified: Session, star_id: np.ndarray) -> Session:
    """``session`` with ``star_id``, the rows ``stars`` taking ``identified``'s identities and places (ra/dec)."""
    star_id[stars] = identified.star_id
    out = replace(session, star_id=star_id)
    if session.ra_deg is not None and identified.ra_deg is not None:
        ra, dec = session.ra_deg.copy(), session.dec_deg.copy()
        ra[stars], dec[stars] = identified.ra_deg, identified.dec_deg
        out = replace(out, ra_deg=ra, dec_deg=dec)
    return out


def identify_then_admit(session: Session, identify, catalogue: Catalogue | None = None):
    """``identify(session)`` (an :class:`hostlink.images.identify.Identification`) on the session without its
    candidates, then the candidates admitted (module docstring) with the camera calibrated on what it identified.
    Returns the identification with every row back in place (candidates not admitted unidentified) and one more
    record in ``rounds``: ``{"round": "guided", ...}`` with the per-frame admissions. BLAS on one thread
    (:func:`hostlink.calibration.data.one_blas_thread`): the products here are thin (the catalogue's directions by
    an attitude, per-frame pairs)."""
    from hostlink.calibration.data import one_blas_thread

    with one_blas_thread():
        return _identify_then_admit(session, identify, catalogue)


def _identify_then_admit(session: Session, identify, catalogue: Catalogue | None):
    """:func:`identify_then_admit`."""
    held = candidate_rows(session)
    if not np.any(held):
        return identify(session)
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
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
    camera = _calibrated(result.session, result.camera)
    if camera is None:
        record.update(
            camera="the identification's (calibration failed)", status="calibration failed: no candidate admitted"
        )
        frames = ()
    else:
        star_id, frames = admit(session, star_id, held, camera, catalogue)
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
    from hostlink.images.identify import _with_identities  # the identified rows' places, as identify fills them

    return replace(result, session=_with_identities(session, star_id, catalogue), rounds=(*result.rounds, record))


def _calibrated(session: Session, camera: CameraParams | None) -> CameraParams | None:
    """The camera calibrated on ``session``'s identified stars (default method), None when that fails."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.errors import UserError

    if camera is None or not np.any(session.star_id != 0):
        return None
    try:
        outcome, _ = calibrate_session(session, camera, keep_failed=True)
    except UserError:
        return None
    return None if outcome.failure() else outcome.params


def admit(
    session: Session, star_id: np.ndarray, held: np.ndarray, camera: CameraParams, catalogue: Catalogue
) -> tuple[np.ndarray, tuple[FrameAdmission, ...]]:
    """``star_id`` with the admitted candidates (rows ``held``) named, frame by frame (module docstring), and each
    frame's :class:`FrameAdmission`."""
    from hostlink.sky.apparent import stars_at_j2000

    sky = stars_at_j2000(catalogue)
    directions = radec_to_unit(sky.ra_rad, sky.dec_rad)
    theta = camera.model_vector(np.float64)
    out = star_id.copy()
    frames = []
    saturated = _flag(session, "saturated")
    sigma_px = _number(session, "sigma_px")
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
            sigma_px[rows],
            theta,
            camera.image_size_px,
            directions,
            catalogue,
        )
        out[rows] = names
        frames.append(replace(record, frame=int(session.frame[rows[0]]) if rows.size else k))
    return out, tuple(frames)


def _flag(session: Session, name: str) -> np.ndarray:
    values = session.extra.get(name) if session.extra else None
    if values is None:
        return np.zeros(len(session), dtype=bool)
    return np.array([str(v).strip() == "1" for v in values], dtype=bool)


def _number(session: Session, name: str) -> np.ndarray:
    values = session.extra.get(name) if session.extra else None
    if values is None:
        return np.full(len(session), np.nan)
    out = np.full(len(session), np.nan)
    for i, v in enumerate(values):
        try:
            out[i] = float(v)
        except (TypeError, ValueError):
            pass
    return out


def _admit_frame(x, y, mag, star_id, held, saturated, sigma_px, theta, image_size_px, directions, catalogue):
    """One frame of :func:`admit`: (its star ids with the admitted candidates named, its :class:`FrameAdmission`)."""
    named = (star_id != 0) & ~held
    if np.count_nonzero(named) < MIN_FRAME_STARS:
        return star_id, FrameAdmission(0, status=f"fewer than {MIN_FRAME_STARS} identified stars")
    cat_rows = np.searchsorted(catalogue.hip, star_id[named])
    fit = _frame_attitude(x[named], y[named], directions[cat_rows], theta)
    if fit is None:
        return star_id, FrameAdmission(0, status="no attitude")
    c, mirrored, sigma_pred = fit
    bright = named & ~saturated & np.isfinite(mag)
    if np.count_nonzero(bright) < MIN_FRAME_STARS:
        return star_id, FrameAdmission(0, status=f"fewer than {MIN_FRAME_STARS} unsaturated identified stars")
    offsets = catalogue.mag[np.searchsorted(catalogue.hip, star_id[bright])] - mag[bright]
    zero_point = float(np.median(offsets))
    scatter = MAD_TO_SIGMA * float(np.median(np.abs(offsets - zero_point)))
    window = max(PHOTOMETRIC_SIGMAS * scatter, MIN_PHOTOMETRIC_WINDOW_MAG)
    near, xp, yp = _predicted(directions, c, theta, mirrored, image_size_px)
    searched = ~np.isin(catalogue.hip[near], star_id[named])
    near, xp, yp = near[searched], xp[searched], yp[searched]
    predicted_mag = catalogue.mag[near] - zero_point  # instrumental
    # every row left unidentified: the candidates, and the detected stars identification could not name (with the
    # calibrated camera the radius is a pixel or less, where the uncalibrated one needed several)
    cand = np.flatnonzero((star_id == 0) & np.isfinite(mag) & np.isfinite(sigma_px) & (sigma_px > 0))
    radius = CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + sigma_px[cand] ** 2)  # per candidate
    # candidate i could be catalogue star j: near enough and as bright as predicted
    d2 = (x[cand, None] - xp[None, :]) ** 2 + (y[cand, None] - yp[None, :]) ** 2
    agree = np.abs(mag[cand, None] - predicted_mag[None, :]) <= window
    within = d2 <= radius[:, None] ** 2
    # ... and every catalogue star whose light could be in this row: unresolved from it, bright enough
    blended = d2 <= np.maximum(radius, UNRESOLVED_PX)[:, None] ** 2
    could_be = blended & (predicted_mag[None, :] <= mag[cand, None] + max(window, COMPANION_MAG))
    match = within & agree
    names = star_id.copy()
    # the row nearest to each prediction, of all the frame's rows (an identified star nearer to it is that star's)
    nearest_row = np.argmin((x[:, None] - xp[None, :]) ** 2 + (y[:, None] - yp[None, :]) ** 2, axis=0)
    admitted = 0
    for i in np.flatnonzero(np.count_nonzero(match, axis=1) == 1):
        j = int(np.flatnonzero(match[i])[0])
        if np.count_nonzero(could_be[i]) != 1 or np.count_nonzero(match[:, j]) != 1:
            continue  # two catalogue stars could be this row, or two rows this star
        if nearest_row[j] != cand[i]:
            continue  # another row is nearer to the prediction
        names[cand[i]] = catalogue.hip[near[j]]
        admitted += 1
    # chance: every candidate whose magnitude agrees with star j, spread over the detector, falling within r of it
    width, height = image_size_px
    expected = float(np.sum(agree * (math.pi * radius**2)[:, None]) / (width * height))
    record = FrameAdmission(0, int(near.size), admitted, expected, sigma_pred, scatter)
    if expected > MAX_FALSE_FRACTION * admitted:
        return star_id, replace(record, admitted=0, status="not admitted: chance too high")
    return names, record


def _frame_attitude(x, y, r, theta):
    """(C, mirrored, sigma_pred [px per axis]) of the frame's identified stars through the camera ``theta`` at the
    parity that fits better (None when degenerate)."""
    best = None
    for mirrored in (False, True):
        xm = 2.0 * theta[1] - x if mirrored else x
        b = pixels_to_unit(xm, y, theta)
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
    if mirrored:
        xp = 2.0 * theta[1] - xp
    on = (xp >= -0.5) & (xp <= width - 0.5) & (yp >= -0.5) & (yp <= height - 0.5)
    return front[on], xp[on], yp[on]
