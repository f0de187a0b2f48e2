"""Lost-in-space identification of a session's unidentified stars (``star_id`` 0) against the bundled Hipparcos
catalogue (issue 11, ``hostlink identify``), tolerant of a nominal focal length off by up to 10 %, unknown distortion,
false stars (hot pixels, noise) and a mirrored detector.

Per frame:

1. Propose: the pattern engine (:mod:`hostlink.images.solver_adapter`, tetra3rs) matches the frame's centroids,
   brightest first, to catalogue 4-star patterns over a field range covering the nominal +-12 %. It tries the
   whole frame, then only the brightest 30, 20, 15 and 10 centroids (false stars among the bright ones spoil its
   patterns). Frames it cannot match go to the project's own pair-anchored matcher (:func:`anchor_candidates`,
   a hypothesise-and-test over catalogue pairs of the same angle) at the focal length the session's identified
   frames measured (one camera for the whole session); without the engine, over a scan of focal lengths. The own
   matcher gives a frame at most :data:`MAX_ANCHOR_PAIRS` anchor pairs (an operation count, in the order of
   :func:`_anchor_schedule`); a frame it has not identified within them is "no match within N anchor pairs".
2. Re-derive with the project's own code, trusting nothing of the engine but its pairs (centroid, Hipparcos number):
   directions b through the nominal camera (for a mirrored detector with x mirrored about the principal point),
   reference directions r at J2000.0 (annual aberration changes an interstar angle by at most 20.5" x the angle in
   radians: 2" over a 6 deg pair, far inside the tolerances below), the focal-length scale from the pairs' own
   interstar angles (:func:`hostlink.calibration.robust.estimate_scale`), and the parity from the handedness of
   star triples (:func:`hostlink.calibration.robust.triple_handedness`): the parity that verifies is kept, whatever
   the engine said.
3. Extend: the attitude (Markley's SVD, :func:`onboard.attitude.attitude_from_vectors`) of the consistent pairs
   predicts where every catalogue star of the field, down to one magnitude fainter than the faintest proposed
   match, falls on the detector; a centroid within :data:`EXTEND_RADIUS_PX` (scaled by the fit's residual) of
   exactly one predicted star, and nearer to it than any other centroid, is a candidate too. Two rounds.
4. Verify: every candidate goes through the project's interstar vote
   (:func:`hostlink.calibration.robust.vote_consistent_stars`, seed 000 eq. 3: interstar angles do not depend on
   the attitude) with the tolerances :data:`VERIFY_REL_TOL` and :data:`VERIFY_ABS_TOL_PX`, and must agree with at
   least :data:`VERIFY_MIN_AGREEMENT` of the others. A frame is accepted only if at least :data:`MIN_VERIFIED`
   stars verify, they are at least :data:`MIN_VERIFIED_FRACTION` of its candidates, and the triple handedness is
   unanimous to :data:`PARITY_MIN_AGREEMENT`; and at least :data:`MIN_COMPLETENESS` of the catalogue stars the
   solution puts on the detector, as bright as its median identified star, must be among the identified (a chance
   alignment of faint stars leaves the bright ones of its field unmatched); a matcher's proposal must also give the
   session's focal-length scale within :data:`SCALE_AGREEMENT`.

After every frame has been tried once, the frames not yet identified are tried again by the engine with the field
of view the identified frames measured and a tolerance of :data:`REFINED_FOV_TOLERANCE`, then by the own matcher.

From 8 to 50 deg fields (issue 30): a frame with :data:`REFINE_MIN_STARS` verified stars refines its own focal
length and radial terms on them (:func:`_refine_radial`), and its later candidates are predicted and verified
through that camera, so the match radius (:func:`_match_radius_px`) follows the centroid noise, not the lens; a star
that two catalogue stars could be is left unidentified (:func:`_ambiguous`); the own matcher's catalogue depth
follows the field (:func:`fallback_depth_mag`); a nominal wider than :data:`MAX_DIAGONAL_FIELD_DEG` (a fisheye) is
refused. :func:`identify_iteratively` identifies, calibrates and identifies again until a round adds nothing.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from hostlink.calibration.data import build_data
from hostlink.calibration.robust import estimate_scale, triple_handedness, vote_consistent_stars
from hostlink.files.session import Session
from hostlink.images import guided, solver_adapter
from hostlink.sky.catalogue import Catalogue
from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad
from onboard.camera import pixels_to_unit, radec_to_unit, unit_to_pixels
from onboard.params import CameraParams

#: Brightest-centroid subsets the engine is tried on after the whole frame (false stars among the brightest
#: centroids spoil its 4-star patterns; a smaller subset of the brightest avoids them).
ENGINE_SUBSETS = (30, 20, 15, 10)
#: Verification: relative interstar-angle tolerance after the scale is estimated. Unknown radial distortion of a
#: few pixels at the edge of a 1000 px detector changes a long pair's angle by a few 1e-3.
VERIFY_REL_TOL = 0.005
#: Verification: absolute interstar tolerance [px, converted to rad by the estimated focal length]: centroid
#: noise of real faint stars (0.3-1 px) plus the unmodelled distortion of a short pair.
VERIFY_ABS_TOL_PX = 3.0
#: Verification: fraction of the other candidates of its frame a star must agree with (a misidentified star agrees
#: with almost none; a true one with all true ones, so it passes while up to 30 % of its frame is wrong).
VERIFY_MIN_AGREEMENT = 0.7
#: A frame's identification is accepted with at least this many verified stars (4 stars give 5 independent
#: interstar angles beyond the attitude: a chance alignment of 4 wrong identities within the tolerance is
#: negligible, and the engine's own false-match probability budget is 1e-5).
MIN_VERIFIED = 4
#: ... and when the verified stars are at least this fraction of the frame's candidates.
MIN_VERIFIED_FRACTION = 0.6
#: Triples of verified stars must agree on the parity at least this often (1.0 for a clean frame; a near-collinear
#: triple with centroid noise can flip, so not all are required).
PARITY_MIN_AGREEMENT = 0.9
#: Extension: a centroid within this many rms residuals of the verified stars (or :data:`EXTEND_RADIUS_PX`,
#: whichever is larger) of a predicted catalogue star is a candidate; the nearest other predicted star must be at
#: least twice as far. The radius follows the camera model's error: several px for an uncalibrated wide lens, about
#: a pixel once calibrated, where a fixed 4 px let false stars meet faint catalogue stars by chance (a 50-deg
#: field holds ~0.5 Hp <= 7.5 stars per square degree: 4 px of 0.94' is a 7 % chance per false star, 1.5 px 1 %).
EXTEND_RADIUS_RESIDUALS = 4.0
EXTEND_RADIUS_PX = 1.5
#: Extension: catalogue stars down to this many magnitudes fainter than the faintest proposed match are predicted.
EXTEND_MAG_MARGIN = 1.0
#: Second pass: field-of-view tolerance once the identified frames have measured the focal length.
REFINED_FOV_TOLERANCE = 0.02
#: Acceptance: of the catalogue stars on the detector at least as bright as the median identified star, at least
#: this fraction must be identified (half of them are identified by construction when all are detected).
MIN_COMPLETENESS = 0.5
#: Acceptance of a fallback (pair-anchored) proposal: its frame's focal-length scale must agree with the session's
#: within this fraction (the identified frames of the real set scatter by +-0.05 %; distortion sampled by a few
#: stars moves a frame's scale by ~0.1 %).
SCALE_AGREEMENT = 0.002
#: Extension rounds (the second uses the attitude refitted with the first round's stars); then more, each to the
#: depth the verified stars reached plus :data:`EXTEND_MAG_MARGIN`, until one adds nothing, at most
#: :data:`MAX_EXTEND_ROUNDS` in all.
EXTEND_ROUNDS = 2
MAX_EXTEND_ROUNDS = 6


@dataclass(frozen=True)
class FrameIdentity:
    """What identification found in one frame.

    frame: the session's frame counter; n_centroids: its unidentified rows (star_id 0); n_candidates: matches
    proposed (engine and extension); n_identified: verified and written; n_ambiguous: verified but left unidentified
    because two catalogue stars could be them (:func:`_ambiguous`); status: ``identified`` or why not;
    attitude: C (3, 3) with b = C r for J2000 directions r (None when not identified); ra_deg, dec_deg: the
    boresight; roll_deg: the angle from the image's -y axis (up) to the projected celestial north, toward +x;
    mirrored: the parity (True: the image is the sky's mirror image; None when unknown); scale: F / F_nominal;
    residual_arcsec: rms of |b - C r| over the identified stars.
    """

    frame: int
    n_centroids: int
    n_candidates: int = 0
    n_identified: int = 0
    status: str = "no match"
    attitude: np.ndarray | None = None
    ra_deg: float = math.nan
    dec_deg: float = math.nan
    roll_deg: float = math.nan
    mirrored: bool | None = None
    scale: float = math.nan
    residual_arcsec: float = math.nan
    n_ambiguous: int = 0

    def as_dict(self) -> dict:
        """JSON-ready report of this frame."""
        return {
            "frame": self.frame,
            "status": self.status,
            "centroids": self.n_centroids,
            "candidates": self.n_candidates,
            "identified": self.n_identified,
            "ambiguous": self.n_ambiguous,
            "ra_deg": _finite(self.ra_deg),
            "dec_deg": _finite(self.dec_deg),
            "roll_deg": _finite(self.roll_deg),
            "parity": None if self.mirrored is None else ("mirrored" if self.mirrored else "normal"),
            "scale": _finite(self.scale),
            "residual_arcsec": _finite(self.residual_arcsec),
            "attitude": None if self.attitude is None else [[float(v) for v in row] for row in self.attitude],
        }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


@dataclass(frozen=True)
class Identification:
    """The result of :func:`identify_session`: the session with the identified rows' ``star_id`` (and ra/dec when
    the file has those columns) filled in, and one :class:`FrameIdentity` per frame that had unidentified rows."""

    session: Session
    frames: tuple[FrameIdentity, ...]
    engine: str
    nominal_fov_deg: float
    #: one record per round of :func:`identify_iteratively` (empty for a single :func:`identify_session`)
    rounds: tuple[dict, ...] = ()
    #: the camera the final round identified with (the nominal, or the calibration of the round before)
    camera: CameraParams | None = None

    @property
    def n_identified(self) -> int:
        return sum(f.n_identified for f in self.frames)

    @property
    def n_frames_identified(self) -> int:
        return sum(f.status == "identified" for f in self.frames)

    @property
    def mirrored(self) -> bool | None:
        """The session's parity: the majority of its identified frames (None when none was identified)."""
        votes = [f.mirrored for f in self.frames if f.status == "identified"]
        return None if not votes else sum(votes) > len(votes) / 2

    @property
    def scale(self) -> float:
        """Median F / F_nominal over the identified frames (NaN when none)."""
        s = [f.scale for f in self.frames if f.status == "identified"]
        return float(np.median(s)) if s else math.nan

    def report(self) -> dict:
        """JSON-ready report: totals, the session's parity and scale, and every frame."""
        return {
            "engine": self.engine,
            "frames": len(self.frames),
            "frames_identified": self.n_frames_identified,
            "stars_identified": self.n_identified,
            "parity": None if self.mirrored is None else ("mirrored" if self.mirrored else "normal"),
            "scale": _finite(self.scale),
            "rounds": list(self.rounds),
            "per_frame": [f.as_dict() for f in self.frames],
        }


@dataclass(frozen=True)
class _Sky:
    """The catalogue as J2000.0 unit vectors, with magnitudes and Hipparcos numbers (sorted, as the catalogue)."""

    hip: np.ndarray
    r: np.ndarray
    mag: np.ndarray


def _sky(catalogue: Catalogue) -> _Sky:
    from hostlink.sky.apparent import stars_at_j2000

    stars = stars_at_j2000(catalogue)
    return _Sky(catalogue.hip, radec_to_unit(stars.ra_rad, stars.dec_rad), catalogue.mag)


def _mirror_x(x_px: np.ndarray, theta: np.ndarray, mirrored: bool) -> np.ndarray:
    """Column coordinates mirrored about the principal point's column when ``mirrored`` (a mirrored detector seen
    through a proper camera), unchanged otherwise."""
    return 2.0 * theta[1] - x_px if mirrored else x_px


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
    best = (theta, c, float(np.sum((pixels_to_unit(x_px, y_px, theta) - r @ c.T) ** 2)))
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
        b = pixels_to_unit(x_px, y_px, current)
        residual = (b - r @ att.T).ravel()
        columns = []
        for index, step in steps.items():
            shifted = current.copy()
            shifted[index] += step
            columns.append(((pixels_to_unit(x_px, y_px, shifted) - b) / step).ravel())
        # the attitude's small rotation phi: C -> (I - [phi x]) C moves b - C r by -(C r) x phi
        cr = r @ att.T
        for axis in np.eye(3):
            columns.append(-np.cross(cr, axis).ravel())
        jac = np.stack(columns, axis=1)
        norm = np.linalg.norm(jac, axis=0)
        if not np.all(norm > 0):
            break
        delta = np.linalg.lstsq(jac / norm, -residual, rcond=None)[0] / norm
        for (index, _), d in zip(steps.items(), delta[:-3], strict=True):
            current[index] += d
        try:
            att = attitude_from_vectors(pixels_to_unit(x_px, y_px, current), r)
        except DegenerateGeometry:
            break
        cost = float(np.sum((pixels_to_unit(x_px, y_px, current) - r @ att.T) ** 2))
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


def _verify(
    x_px, y_px, r, theta, mirrored: bool, scale: float | None = None, prune: bool = False, r_corner_px: float = 0.0
) -> _Verified:
    """The project's own checks of candidate pairs (module docstring, steps 2 and 4) at one parity. ``scale``: the
    focal-length scale when already known (else estimated from the pairs); ``prune``: drop the least consistent
    candidates first (:data:`PRUNE_MIN_AGREEMENT`), for proposals with many wrong pairs. ``r_corner_px``: the
    detector's half-diagonal (:data:`REFINE_K2_SPAN`; 0: the farthest candidate's radius)."""
    n = x_px.shape[0]
    nothing = _Verified(np.zeros(n, dtype=bool), mirrored, math.nan, math.nan, None, None)
    if n < 3:
        return nothing
    data = build_data(_mirror_x(x_px, theta, mirrored), y_px, r, np.zeros(n, dtype=np.int64))
    if scale is None:
        scale, n_pairs = estimate_scale(data, theta)
        if n_pairs == 0:
            return nothing
    theta_s = np.array(theta, dtype=np.float64)
    theta_s[0] *= scale
    b = pixels_to_unit(data.x_px, data.y_px, theta_s)
    tolerances = {"rel_tol": VERIFY_REL_TOL, "abs_tol_rad": VERIFY_ABS_TOL_PX / theta_s[0]}
    alive = np.ones(n, dtype=bool)
    while prune and np.count_nonzero(alive) >= 3:
        sub = np.flatnonzero(alive)
        part, _, _ = data.select(alive, min_stars=1)
        ok = vote_consistent_stars(part, b[sub], min_agreement=PRUNE_MIN_AGREEMENT, **tolerances)
        if np.all(ok):
            break
        alive[sub[~ok]] = False
    keep = np.zeros(n, dtype=bool)
    sub = np.flatnonzero(alive)
    if sub.size >= 3:
        part, _, _ = data.select(alive, min_stars=1)
        keep[sub] = vote_consistent_stars(part, b[sub], min_agreement=VERIFY_MIN_AGREEMENT, **tolerances)
    if np.count_nonzero(keep) < 3:
        return _Verified(keep, mirrored, scale, math.nan, None, None)
    opposite, total = triple_handedness(data, b, keep)
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
) -> tuple[np.ndarray, np.ndarray]:
    """Candidates beyond the proposal's (module docstring, step 3): (rows into the frame, sky indices)."""
    near, xp, yp = _predict(sky, theta, v, image_size_px, mag_limit)
    if near.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    radius = _match_radius_px(theta, v)
    d2 = (x_px[:, None] - xp[None, :]) ** 2 + (y_px[:, None] - yp[None, :]) ** 2  # (centroids, predicted)
    rows, stars = [], []
    for i in range(x_px.shape[0]):
        if taken_rows[i]:
            continue
        order = np.argsort(d2[i])
        j = int(order[0])
        if d2[i, j] > radius * radius:
            continue
        if order.size > 1 and d2[i, int(order[1])] < 4.0 * d2[i, j]:
            continue  # two catalogue stars nearly as close: ambiguous
        if int(np.argmin(d2[:, j])) != i:
            continue  # another centroid is nearer to this star
        rows.append(i)
        stars.append(int(near[j]))
    return np.asarray(rows, dtype=np.int64), np.asarray(stars, dtype=np.int64)


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
) -> np.ndarray:
    """(K,) bool over the candidates (centroids ``x_px, y_px`` named ``stars``): another catalogue star, no fainter
    than its own identity by more than :data:`AMBIGUITY_MAG_MARGIN` and within ``mag_limit``, is predicted by the
    verified solution within :func:`_match_radius_px` of the centroid: two catalogue stars could be this star (a
    close pair the detector does not resolve, or either of two), so it is left unidentified."""
    near, xp, yp = _predict(sky, theta, v, image_size_px, mag_limit)
    out = np.zeros(stars.size, dtype=bool)
    if near.size < 2:
        return out
    radius = _match_radius_px(theta, v)
    d2 = (x_px[:, None] - xp[None, :]) ** 2 + (y_px[:, None] - yp[None, :]) ** 2
    other = (d2 <= radius * radius) & (near[None, :] != stars[:, None])
    bright_enough = sky.mag[near][None, :] <= sky.mag[stars][:, None] + AMBIGUITY_MAG_MARGIN
    return np.any(other & bright_enough, axis=1)


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


@dataclass(frozen=True)
class PairCatalogue:
    """Every pair of catalogue stars closer than ``max_angle_rad``, sorted by angle: the fallback matcher's index.

    a, b: (P,) int64 indices into the :class:`_Sky` arrays; angle_rad: (P,) their separations, ascending;
    r: the sky's unit vectors (indexed by a and b); rows: the sky indices of the stars taking part (brighter than
    the limit), and tree: a k-d tree of their unit vectors (``scipy.spatial.cKDTree``)."""

    a: np.ndarray
    b: np.ndarray
    angle_rad: np.ndarray
    max_angle_rad: float
    r: np.ndarray
    rows: np.ndarray
    tree: object
    #: (S,) uint16: each sky star's rank among ``rows`` (None when more than 65536 stars take part): a 16-bit sort
    #: key, which numpy's stable sort orders in linear time (radix sort), for :func:`_pairs_of_angle`
    rank16: np.ndarray | None = None


def pair_catalogue(sky: _Sky, max_angle_rad: float, maglim: float) -> PairCatalogue:
    """The pairs of stars brighter than ``maglim`` within ``max_angle_rad`` (a k-d tree on the unit vectors,
    ``scipy.spatial.cKDTree.query_pairs`` with the chord 2 sin(angle / 2))."""
    from scipy.spatial import cKDTree

    rows = np.flatnonzero(sky.mag <= maglim)
    chord = 2.0 * math.sin(0.5 * max_angle_rad)
    tree = cKDTree(sky.r[rows])
    pairs = tree.query_pairs(chord, output_type="ndarray")
    a, b = rows[pairs[:, 0]], rows[pairs[:, 1]]
    dot = np.clip(np.sum(sky.r[a] * sky.r[b], axis=1), -1.0, 1.0)
    angle = np.arccos(dot)
    order = np.argsort(angle, kind="stable")
    rank16 = None
    if rows.size <= 1 << 16:
        rank16 = np.zeros(sky.r.shape[0], dtype=np.uint16)
        rank16[rows] = np.arange(rows.size, dtype=np.uint16)
    return PairCatalogue(a[order], b[order], angle[order], max_angle_rad, sky.r, rows, tree, rank16)


#: Fallback matcher: the brightest centroids of a frame it uses; pairs among the first ANCHOR_STARS are anchors.
MATCH_STARS = 20
ANCHOR_STARS = 7
#: Fallback matcher, second round at a known scale for frames the first did not identify (faint fields where
#: noise outranks some stars): deeper, and about 5 x slower.
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


def _triad_inverse(b1, b2, r1, r2) -> np.ndarray:
    """C^T (M, 3, 3) of the TRIAD attitudes (Black 1964) mapping r1 -> b1 exactly and r2 toward b2: b = C r."""

    def frame(v1, v2):
        t2 = np.cross(v1, v2)
        t2 /= np.linalg.norm(t2, axis=-1, keepdims=True)
        return np.stack([v1, t2, np.cross(v1, t2)], axis=-1)  # columns t1, t2, t3

    return frame(r1, r2) @ np.swapaxes(frame(b1, b2), -1, -2)


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
    lo, hi = np.searchsorted(pairs.angle_rad, [angle_rad - slack_rad, angle_rad + slack_rad])
    star = np.concatenate([pairs.a[lo:hi], pairs.b[lo:hi]])
    other = np.concatenate([pairs.b[lo:hi], pairs.a[lo:hi]])
    count = np.bincount(star, minlength=pairs.r.shape[0])
    offset = np.concatenate([[0], np.cumsum(count)])
    key = star if pairs.rank16 is None else pairs.rank16[star]  # the same order: rows ascend with the sky index
    return _PairsOfAngle(angle_rad, slack_rad, offset, other[np.argsort(key, kind="stable")], count > 0)


def _pyramid_may_hit(
    r: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    with_first: _PairsOfAngle | None,
    with_second: _PairsOfAngle | None,
) -> np.ndarray:
    """(M,) bool: the anchor hypotheses (``first``, ``second``: sky indices of the anchor stars b_i, b_j; ``r``: the
    sky's unit vectors) that can put a third star b_m within the hit chord c of a catalogue star s at all: a
    necessary condition only (the k-d tree decides). A hypothesis (TRIAD) maps b_i onto its first star exactly,
    b_j onto the great circle toward its second star, off it by the pair's angle mismatch d (at most the anchor
    window's tolerance), and preserves angles. So s lies at the angle (b_i, b_m) from the first star to within
    the angle 2 asin(c / 2) < 1.001 c that the chord subtends, and at (b_j, b_m) from the second to within
    1.001 c + d: s is a partner of the first star in ``with_first`` and of the second in ``with_second``, the pairs
    of those angles with slacks of at least that. A side given as None is not tested."""
    may = np.ones(first.size, dtype=bool)
    for side, stars in ((with_first, first), (with_second, second)):  # each anchor star has such a partner
        if side is not None:
            may &= side.member[stars]
    if with_first is None or with_second is None:
        return may
    # ... and one and the same s: every partner s of the first star, at the second angle from the second star
    cand = np.flatnonzero(may)
    lo = with_first.offset[first[cand]]
    count = with_first.offset[first[cand] + 1] - lo
    # the partners' positions: lo of its hypothesis plus the rank within it (one repeat of the per-hypothesis shift)
    hyp = np.repeat(cand, count)
    s = with_first.partner[np.arange(hyp.size) + np.repeat(lo - (np.cumsum(count) - count), count)]
    # |angle - with_second.angle_rad| <= slack as cosines (arccos decreases on [0, pi]; the window starts above 0)
    dot = np.einsum("ij,ij->i", r[second[hyp]], r[s])
    cos_hi = math.cos(with_second.angle_rad - with_second.slack_rad)
    cos_lo = math.cos(min(with_second.angle_rad + with_second.slack_rad, math.pi))
    may[:] = False
    may[hyp[(dot >= cos_lo) & (dot <= cos_hi)]] = True
    return may


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
    pyramid's pruning); the tree is asked only about the hypotheses a necessary condition on the catalogue pairs
    leaves (:func:`_pyramid_may_hit`), which changes no answer and skips most of the work on a narrow field.
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
        lo, hi = np.searchsorted(pairs.angle_rad, [ang - tol, ang + tol])
        if hi <= lo:
            continue
        first = np.concatenate([pairs.a[lo:hi], pairs.b[lo:hi]])
        second = np.concatenate([pairs.b[lo:hi], pairs.a[lo:hi]])
        others = np.array([m for m in range(k) if m not in (i, j)])
        thirds = [m for m in range(min(k, anchor_stars)) if m not in (i, j)]
        if not thirds:
            continue
        # pyramid pruning, first a necessary condition (the pair index's stars are the tree's): a hypothesis that
        # cannot put any third anchor star on a catalogue star is dropped before its attitude is computed
        may_hit = np.ones((len(thirds), first.size), dtype=bool)
        if tree is pairs.tree:
            for t, m in enumerate(thirds):
                may_hit[t] = _pyramid_may_hit(
                    pairs.r, first, second, pairs_of(i, m, slack_first_rad), pairs_of(j, m, slack_second_rad)
                )
            kept = np.flatnonzero(np.any(may_hit, axis=0))
            first, second, may_hit = first[kept], second[kept], may_hit[:, kept]
            if kept.size == 0:
                continue
        for mirrored in (False, True):
            bm = b * np.array([-1.0, 1.0, 1.0]) if mirrored else b
            c_t = _triad_inverse(bm[i][None], bm[j][None], pairs.r[first], pairs.r[second])
            # pyramid pruning: a hypothesis must first put one more anchor star on a catalogue star
            alive = np.zeros(first.size, dtype=bool)
            for m, may in zip(thirds, may_hit, strict=True):
                ask = np.flatnonzero(may & ~alive)
                if ask.size:
                    dist, _ = tree.query((c_t @ bm[m])[ask], distance_upper_bound=hit_chord)
                    alive[ask[np.isfinite(dist)]] = True
            live = np.flatnonzero(alive)
            if live.size == 0:
                continue
            predicted = np.einsum("mij,kj->mki", c_t[live], bm[others])
            dist, idx = tree.query(predicted.reshape(-1, 3), distance_upper_bound=hit_chord)
            idx = idx.reshape(live.size, others.size)
            star = tree_rows[np.minimum(idx, tree_rows.size - 1)]
            # a hit on one of the anchors' own catalogue stars (a close double) is no evidence
            hits = np.isfinite(dist).reshape(live.size, others.size)
            hits &= (star != first[live][:, None]) & (star != second[live][:, None])
            count = hits.sum(axis=1)
            best = int(np.argmax(count))
            if count[best] >= MIN_HITS:
                got = hits[best]
                h = live[best]
                rows = np.concatenate([[i, j], others[got]]).astype(np.int64)
                stars = np.concatenate([[first[h], second[h]], star[best][got]]).astype(np.int64)
                yield rows, stars, mirrored


def _boresight_and_roll(c: np.ndarray) -> tuple[float, float, float]:
    """Boresight (ra, dec) [deg] and roll [deg]: the angle from the image's -y axis (up) to the celestial north
    projected into the image, measured toward +x (the one formula: :func:`hostlink.sky.pointing.boresight_radec_roll`,
    which ``hostlink attitude`` writes too)."""
    from hostlink.sky.pointing import boresight_radec_roll

    return boresight_radec_roll(c)


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
    stars ``rows`` named ``stars`` (NaN without magnitudes)."""
    if mag is None or rows.size == 0:
        return math.nan
    offset = sky.mag[stars] - mag[rows]
    offset = offset[np.isfinite(offset)]
    return float(np.median(offset)) if offset.size else math.nan


def _too_faint(mag: np.ndarray | None, rows: np.ndarray, stars: np.ndarray, sky: _Sky, zero_point: float) -> np.ndarray:
    """(K,) bool: the candidates whose catalogue star is more than :data:`PHOTOMETRIC_TOL_MAG` fainter than their
    centroid's instrumental magnitude plus ``zero_point`` implies (False where either is unknown)."""
    if mag is None or not math.isfinite(zero_point):
        return np.zeros(rows.size, dtype=bool)
    with np.errstate(invalid="ignore"):
        return sky.mag[stars] > mag[rows] + zero_point + PHOTOMETRIC_TOL_MAG


def _faintest_detectable(mag: np.ndarray | None, zero_point: float) -> float:
    """The faintest catalogue magnitude a candidate of the frame may have (:func:`_too_faint` of its faintest
    centroid); +inf when unknown."""
    if mag is None or not math.isfinite(zero_point) or not np.any(np.isfinite(mag)):
        return math.inf
    return float(np.nanmax(mag)) + zero_point + PHOTOMETRIC_TOL_MAG


def _confirm(
    ident: FrameIdentity,
    x_px: np.ndarray,
    y_px: np.ndarray,
    rows: np.ndarray,
    stars: np.ndarray,
    mirrored_hint: bool,
    theta: np.ndarray,
    sky: _Sky,
    image_size_px: tuple[int, int],
    scale: float | None = None,
    mag: np.ndarray | None = None,
) -> tuple[FrameIdentity, np.ndarray]:
    """Verify, extend and verify again a proposal (module docstring, steps 2-4): the frame's identity and the
    (N,) Hipparcos number of each centroid (0 where not identified). ``scale``: F / F_nominal when known (a
    matcher's proposal, whose wrong pairs are then pruned), else estimated from the proposal. ``mag``: the
    centroids' instrumental magnitudes, when known: candidates far too faint for them are dropped
    (:func:`_too_faint`) and the extension goes no deeper than the frame's faintest centroid implies."""
    n = x_px.shape[0]
    hip_out = np.zeros(n, dtype=np.int64)
    n_proposed = int(rows.size)
    r_corner = 0.5 * math.hypot(*image_size_px)
    v = _verify_best_parity(
        x_px[rows], y_px[rows], sky.r[stars], theta, mirrored_hint, scale, scale is not None, r_corner
    )
    if v.attitude is None:
        return replace(ident, n_candidates=n_proposed, status="not verified"), hip_out
    mag_limit = float(np.max(sky.mag[stars[v.keep]])) + EXTEND_MAG_MARGIN
    theta_frame = theta  # the camera later rounds verify through: the frame's own once refined
    for round_no in range(MAX_EXTEND_ROUNDS):
        taken = np.zeros(n, dtype=bool)
        taken[rows[v.keep]] = True
        zero_point = _zero_point(mag, rows[v.keep], stars[v.keep], sky)
        mag_limit = min(mag_limit, _faintest_detectable(mag, zero_point))
        new_rows, new_stars = _extend(x_px, y_px, sky, theta, v, taken, mag_limit, image_size_px)
        fits = ~_too_faint(mag, new_rows, new_stars, sky, zero_point)
        new_rows, new_stars = new_rows[fits], new_stars[fits]
        if round_no >= EXTEND_ROUNDS and new_rows.size == 0:
            break  # nothing new: the solution is complete at this depth
        rows = np.concatenate([rows[v.keep], new_rows])
        stars = np.concatenate([stars[v.keep], new_stars])
        if v.theta is not None:
            theta_frame = v.theta  # a wide lens's edge stars verify through the lens the frame measured
        v = _verify(x_px[rows], y_px[rows], sky.r[stars], theta_frame, v.mirrored, r_corner_px=r_corner)
        if v.attitude is None:
            return replace(ident, n_candidates=n_proposed, status="not verified"), hip_out
        # deeper as the verified stars go deeper (a proposal of bright stars alone reaches the frame's faint ones)
        mag_limit = max(mag_limit, float(np.max(sky.mag[stars[v.keep]])) + EXTEND_MAG_MARGIN)
    v = replace(v, keep=v.keep & ~_too_faint(mag, rows, stars, sky, _zero_point(mag, rows[v.keep], stars[v.keep], sky)))
    ambiguous = v.keep & _ambiguous(x_px[rows], y_px[rows], stars, sky, theta, v, image_size_px, mag_limit)
    n_ambiguous = int(np.count_nonzero(ambiguous))
    v = replace(v, keep=v.keep & ~ambiguous)
    n_ok = int(np.count_nonzero(v.keep))
    ident = replace(
        ident,
        n_candidates=max(n_proposed, int(rows.size)),
        mirrored=v.mirrored,
        scale=_absolute_scale(v, theta),
        n_ambiguous=n_ambiguous,
    )
    if n_ok < MIN_VERIFIED:
        return replace(ident, status=f"only {n_ok} stars verified (need {MIN_VERIFIED})"), hip_out
    if n_ok < MIN_VERIFIED_FRACTION * rows.size:
        return replace(ident, status=f"only {n_ok} of {rows.size} candidates verified"), hip_out
    if not v.parity_agreement >= PARITY_MIN_AGREEMENT:
        return replace(ident, status="parity not unanimous"), hip_out
    completeness = _completeness(sky, theta, v, image_size_px, stars[v.keep], x_px, y_px)
    if completeness < MIN_COMPLETENESS:
        return replace(ident, status=f"only {100 * completeness:.0f} % of the bright stars in the field found"), hip_out
    if scale is not None and abs(ident.scale / scale - 1.0) > SCALE_AGREEMENT:
        return replace(ident, status=f"scale {ident.scale:.4f} disagrees with the session's {scale:.4f}"), hip_out
    hip_out[rows[v.keep]] = sky.hip[stars[v.keep]]
    ra, dec, roll = _boresight_and_roll(v.attitude)
    rms = float(np.sqrt(np.mean(v.residual_rad[v.keep] ** 2))) * 206264.80624709636
    identified = replace(
        ident,
        n_identified=n_ok,
        status="identified",
        attitude=v.attitude,
        ra_deg=ra,
        dec_deg=dec,
        roll_deg=roll,
        residual_arcsec=rms,
    )
    return identified, hip_out


def _engine_proposal(x_px, y_px, order, brightness, nominal, theta, sky, database, fov_deg, fov_tolerance):
    """The pattern engine's matches (rows, sky indices, its parity), or None."""
    n = x_px.shape[0]
    for size in (n, *(s for s in ENGINE_SUBSETS if s < n)):
        sub = order[:size]
        match = solver_adapter.solve_frame(
            database,
            x_px[sub] - theta[1],
            y_px[sub] - theta[2],
            None if brightness is None else brightness[sub],
            nominal.image_size_px,
            fov_deg,
            fov_tolerance,
        )
        if match is not None:
            idx = np.searchsorted(sky.hip, match.hip)
            found = (idx < sky.hip.size) & (sky.hip[np.minimum(idx, sky.hip.size - 1)] == match.hip)
            return sub[match.rows][found], idx[found], match.mirrored
    return None


def identify_frame(
    frame: int,
    x_px: np.ndarray,
    y_px: np.ndarray,
    mag: np.ndarray | None,
    nominal: CameraParams,
    sky: _Sky,
    database,
    fov_deg: float,
    fov_tolerance: float,
    pairs: PairCatalogue | None = None,
    scales: tuple[float, ...] = (),
) -> tuple[FrameIdentity, np.ndarray]:
    """Identify one frame's centroids (module docstring). The engine (when ``database`` is given) proposes first;
    then, with ``pairs``, the pair-anchored matcher (:func:`anchor_candidates`) at each focal-length scale of ``scales``
    (F / F_nominal). Returns its :class:`FrameIdentity` and the (N,) int64 Hipparcos number of each centroid (0
    where not identified)."""
    n = x_px.shape[0]
    ident = FrameIdentity(frame=frame, n_centroids=n)
    if n < solver_adapter.MIN_CENTROIDS:
        return replace(ident, status=f"too few centroids ({n})"), np.zeros(n, dtype=np.int64)
    theta = nominal.model_vector(np.float64)
    if mag is not None and not np.any(np.isfinite(mag)):
        mag = None  # no brightness at all: the file's order stands
    order = np.argsort(np.where(np.isfinite(mag), mag, np.inf), kind="stable") if mag is not None else np.arange(n)
    brightness = None if mag is None else np.where(np.isfinite(mag), 10.0 ** (-0.4 * mag), 0.0)
    best = (ident, np.zeros(n, dtype=np.int64))
    if database is not None:
        proposal = _engine_proposal(
            x_px, y_px, order, brightness, nominal, theta, sky, database, fov_deg, fov_tolerance
        )
        if proposal is not None:
            best = _confirm(ident, x_px, y_px, *proposal, theta, sky, nominal.image_size_px, mag=mag)
            if best[0].status == "identified":
                return best
    if pairs is None:
        return best
    known = len(scales) == 1
    rounds = [(MATCH_STARS, ANCHOR_STARS, 0)] + ([(DEEP_MATCH_STARS, DEEP_ANCHOR_STARS, ANCHOR_STARS)] if known else [])
    rel_tol = ANCHOR_REL_TOL_KNOWN if known else ANCHOR_REL_TOL
    budget, cut = MAX_ANCHOR_PAIRS, False
    for n_match, n_anchor, skip in rounds:
        bright = order[:n_match]
        for scale, anchor_pairs in _anchor_schedule(min(n, n_match), n_anchor, skip, scales):
            if budget < len(anchor_pairs):  # the budget is spent: the rest is not tried
                anchor_pairs = anchor_pairs[:budget]
                cut = True
            budget -= len(anchor_pairs)
            theta_s = np.array(theta, dtype=np.float64)
            theta_s[0] *= scale
            b = pixels_to_unit(x_px[bright], y_px[bright], theta_s)
            proposals = anchor_candidates(
                b, pairs, pairs.tree, pairs.rows, theta_s[0], n_anchor, rel_tol, anchor_pairs=anchor_pairs
            )
            for rows, stars, mirrored in proposals:
                result = _confirm(
                    ident, x_px, y_px, bright[rows], stars, mirrored, theta, sky, nominal.image_size_px, scale, mag
                )
                if result[0].status == "identified":
                    return result
                if result[0].n_candidates > best[0].n_candidates:
                    best = result
            if cut:
                status = f"no match within {MAX_ANCHOR_PAIRS} anchor pairs"
                return replace(best[0], status=f"{status} ({best[0].status})"), best[1]
    return best


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
FALLBACK_DEPTH_PERCENTILE = 90


#: Frames the own matcher scans over every focal-length scale when the engine is installed but matched no frame
#: (about 5 s per frame for the 51 scales): the cost stays bounded, and one identified frame gives every other its
#: scale.
ENGINE_MISS_SCANNED_FRAMES = 3


@dataclass(frozen=True)
class _SessionContext:
    """What every frame of one :func:`identify_session` call shares: the session, the nominal camera and its
    horizontal field [deg], the catalogue as unit vectors, and the engine's pattern database (None without it)."""

    session: Session
    nominal: CameraParams
    fov_deg: float
    sky: _Sky
    database: object


def _identify_frame_k(
    ctx: _SessionContext, k: int, database, fov_deg: float, tol: float, pairs=None, scales=()
) -> tuple[FrameIdentity, np.ndarray]:
    """:func:`identify_frame` on the unidentified rows of the session's ``k``-th frame."""
    session, starts = ctx.session, ctx.session.frame_starts
    a, b = int(starts[k]), int(starts[k + 1])
    rows = a + np.flatnonzero(session.star_id[a:b] == 0)
    mag = None if session.mag is None else session.mag[rows]
    return identify_frame(
        int(session.frame[a]),
        session.x_px[rows],
        session.y_px[rows],
        mag,
        ctx.nominal,
        ctx.sky,
        database,
        fov_deg,
        tol,
        pairs,
        scales,
    )


def _identified(results: dict[int, tuple[FrameIdentity, np.ndarray]], k: int) -> bool:
    return k in results and results[k][0].status == "identified"


def _fallback_pairs(ctx: _SessionContext, todo: list[int], results: dict) -> PairCatalogue:
    """The own matcher's pair index: as deep as the identified frames see (:data:`FALLBACK_DEPTH_PERCENTILE` of
    their stars' magnitudes plus :data:`FALLBACK_MAG_MARGIN`), but no deeper than the field's size needs
    (:func:`fallback_depth_mag`; the matcher works on the brightest centroids, and a 50-deg field's pairs to Hp 7.5
    take 40 s to index, to Hp 5.5 a second); pairs as wide as the detector's diagonal at the smallest scanned scale."""
    sky, nominal = ctx.sky, ctx.nominal
    found = [k for k in todo if _identified(results, k)]
    hips = np.concatenate([results[k][1] for k in found]) if found else np.zeros(0, np.int64)
    hips = hips[hips != 0]
    field_depth = fallback_depth_mag(sky.mag, _field_sr(nominal))
    depth = (
        min(
            float(np.percentile(sky.mag[np.searchsorted(sky.hip, hips)], FALLBACK_DEPTH_PERCENTILE))
            + FALLBACK_MAG_MARGIN,
            field_depth + FALLBACK_MAG_MARGIN,
        )
        if hips.size
        else field_depth
    )
    width, height = nominal.image_size_px
    half_diagonal = 0.5 * math.hypot(width, height) / (nominal.focal_length_px * min(SCAN_SCALES))
    return pair_catalogue(sky, 2.0 * math.atan(half_diagonal), depth)


def _engine_pass(ctx: _SessionContext, todo: list[int], progress) -> dict[int, tuple[FrameIdentity, np.ndarray]]:
    """Every frame through the engine at the nominal field (module docstring, step 1)."""
    results = {}
    for done, k in enumerate(todo):
        results[k] = _identify_frame_k(ctx, k, ctx.database, ctx.fov_deg, solver_adapter.FOV_MARGIN)
        if progress is not None:
            progress(done + 1, len(todo))
    return results


def _fallback_pass(ctx: _SessionContext, todo: list[int], results: dict) -> None:
    """The frames the engine left, through the own matcher (updating ``results``): at the engine's measured scale,
    or by a scan of scales (slow: up to :data:`MAX_ANCHOR_PAIRS` anchor pairs, ~0.1 s each): every frame when the
    engine is not there; when it is there but matched no frame (its patterns need stars the frames may lack), at most
    :data:`ENGINE_MISS_SCANNED_FRAMES` frames are scanned, the others then tried at the scale the first identified
    one measured (one camera for the session: the other frames need no scan)."""
    failed = [k for k in todo if not _identified(results, k)]
    if not failed:
        return
    width = ctx.nominal.image_size_px[0]
    engine_scale_known = any(_identified(results, k) for k in results)
    scan_budget = ENGINE_MISS_SCANNED_FRAMES if ctx.database is not None and not engine_scale_known else len(failed)
    scales = [results[k][0].scale for k in todo if _identified(results, k)]
    scale = float(np.median(scales)) if scales else math.nan
    pairs = _fallback_pairs(ctx, todo, results)
    tried_without_scale = []
    for k in failed:
        known = math.isfinite(scale)
        if not known and scan_budget <= 0:
            tried_without_scale.append(k)  # tried below, should a scanned frame measure the scale
            continue
        scan_budget -= 0 if known else 1
        refined = (
            solver_adapter.horizontal_fov_deg(ctx.nominal.focal_length_px * scale, width) if known else ctx.fov_deg
        )
        tol = REFINED_FOV_TOLERANCE if known else solver_adapter.FOV_MARGIN
        retry = _identify_frame_k(ctx, k, ctx.database, refined, tol, pairs, (scale,) if known else SCAN_SCALES)
        if k not in results or retry[0].status == "identified" or retry[0].n_candidates > results[k][0].n_candidates:
            results[k] = retry
        if not known and retry[0].status == "identified":
            scale = retry[0].scale
        elif not known:
            tried_without_scale.append(k)
    if math.isfinite(scale):
        refined = solver_adapter.horizontal_fov_deg(ctx.nominal.focal_length_px * scale, width)
        for k in tried_without_scale:  # the frames scanned before the session's scale was known
            retry = _identify_frame_k(ctx, k, None, refined, REFINED_FOV_TOLERANCE, pairs, (scale,))
            if retry[0].status == "identified":
                results[k] = retry


def identify_session(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue | None = None,
    maglim: float | None = None,
    use_engine: bool = True,
    progress=None,
    database_fov_deg: float | None = None,
) -> Identification:
    """Identify every frame's unidentified rows (module docstring). ``nominal``: the camera as its user knows it
    (focal length within 10 %); ``catalogue``: default the bundled Hipparcos; ``maglim``: only stars at least this
    bright [Hp mag] (default all). ``use_engine``: False (or tetra3rs not installed) identifies with the project's
    own pair-anchored matcher alone. Rows already identified are kept as they are. ``progress(done, total)`` is called
    after each frame. The returned session has the identified rows' star_id (and ra_deg/dec_deg when the file has
    them: the geocentric apparent place with the time known, the J2000 place without) filled in. Stages: the engine
    (:func:`_engine_pass`), the own matcher for the frames it left (:func:`_fallback_pass`), the identities written."""
    check_field(nominal)
    if np.any(guided.candidate_rows(session)):  # faint candidates build no pattern (guided.py)
        return guided.identify_without_candidates(
            session, lambda s: identify_session(s, nominal, catalogue, maglim, use_engine, progress, database_fov_deg)
        )
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    if maglim is not None:
        catalogue = catalogue.subset(np.flatnonzero(catalogue.mag <= maglim))
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, nominal.image_size_px[0])
    engine = use_engine and solver_adapter.engine_available()
    # ``database_fov_deg``: a later round of :func:`identify_iteratively` reuses the first round's database
    database = solver_adapter.pattern_database(catalogue, database_fov_deg or fov, maglim) if engine else None
    ctx = _SessionContext(session, nominal, fov, _sky(catalogue), database)
    starts = session.frame_starts
    todo = [k for k in range(session.n_frames) if np.any(session.star_id[starts[k] : starts[k + 1]] == 0)]
    results = _engine_pass(ctx, todo, progress) if engine else {}
    _fallback_pass(ctx, todo, results)
    star_id = session.star_id.copy()
    for k in todo:
        a, b = int(starts[k]), int(starts[k + 1])
        star_id[a + np.flatnonzero(session.star_id[a:b] == 0)] = results[k][1]
    out = _with_identities(session, star_id, catalogue)
    name = solver_adapter.ENGINE_NAME + " + pair-anchored matching" if engine else "pair-anchored matching"
    return Identification(out, tuple(results[k][0] for k in todo), name, fov)


#: The widest diagonal field [deg] the camera model (a pinhole with polynomial distortion, docs/camera-model.md)
#: describes: at 60 deg off axis a fisheye's equidistant image (r = f theta) lies 40 % inside the pinhole's
#: (r = f tan theta), more than the polynomial's few-% corrections can bend, and at 90 deg the pinhole has none.
MAX_DIAGONAL_FIELD_DEG = 120.0


def diagonal_field_deg(camera: CameraParams) -> float:
    """The detector's diagonal field through the pinhole of ``camera`` [deg]."""
    width, height = camera.image_size_px
    return math.degrees(2.0 * math.atan(0.5 * math.hypot(width, height) / camera.focal_length_px))


def check_field(camera: CameraParams) -> None:
    """A one-line :class:`UserError` for a lens too wide for the camera model (:data:`MAX_DIAGONAL_FIELD_DEG`)."""
    from hostlink.errors import UserError

    field = diagonal_field_deg(camera)
    if field > MAX_DIAGONAL_FIELD_DEG:
        raise UserError(
            f"the nominal camera sees {field:.0f} deg across the diagonal: a lens this wide (a fisheye) is outside "
            f"the camera model (a pinhole with polynomial distortion, up to {MAX_DIAGONAL_FIELD_DEG:.0f} deg); "
            "check the nominal focal length"
        )


def _field_sr(camera: CameraParams) -> float:
    """The detector's field [sr] through the pinhole of ``camera`` (4 asin(sin(a) sin(b)) for a rectangle of half
    angles a, b about the axis)."""
    width, height = camera.image_size_px
    a = math.atan(0.5 * width / camera.focal_length_px)
    b = math.atan(0.5 * height / camera.focal_length_px)
    return 4.0 * math.asin(math.sin(a) * math.sin(b))


def _with_identities(session: Session, star_id: np.ndarray, catalogue: Catalogue) -> Session:
    """``session`` with ``star_id``; when the file has ra_deg/dec_deg, the newly identified rows get theirs (the
    geocentric apparent place at the frame's time, docs/file-formats.md; the J2000 place when the time is unknown)."""
    out = replace(session, star_id=star_id)
    if session.ra_deg is None or session.dec_deg is None:
        return out
    new = np.flatnonzero((star_id != 0) & (session.star_id == 0))
    ra, dec = session.ra_deg.copy(), session.dec_deg.copy()
    if new.size:
        from hostlink.sky.apparent import apparent_radec_deg, hip_lookup, stars_at_j2000

        cat_rows = hip_lookup(catalogue, star_id[new])
        if session.time_known:
            jd1, jd2 = session.frame_times_jd()
            frame_of_row = np.repeat(np.arange(jd1.size), np.diff(session.frame_starts))[new]
            ra[new], dec[new] = apparent_radec_deg(catalogue, cat_rows, jd1[frame_of_row], jd2[frame_of_row])
        else:
            stars = stars_at_j2000(catalogue, cat_rows)
            ra[new], dec[new] = np.degrees(stars.ra_rad), np.degrees(stars.dec_rad)
    return replace(out, ra_deg=ra, dec_deg=dec)


#: :func:`identify_iteratively`: rounds at most (the first with the nominal camera). Each later round identifies
#: with the camera calibrated on the round before; on the real sets the second round adds the field-edge stars an
#: uncalibrated model misplaces and the third adds nothing.
MAX_ROUNDS = 4


def identify_iteratively(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue | None = None,
    maglim: float | None = None,
    use_engine: bool = True,
    max_rounds: int = MAX_ROUNDS,
    progress=None,
) -> Identification:
    """:func:`_identify_iteratively`; a session found mirrored (odd parity, which the calibration refuses: its
    rounds and the guided admission would end at the first calibration) is identified again with x flipped,
    x -> width - 1 - x, and the nominal with it (:func:`flipped_x_camera`), then written back in its own columns.
    Its frames keep the parity ``mirrored`` and the attitude of the mirrored-back columns (as a mirrored frame's
    always was: x mirrored about the principal point); ``camera`` is that of the flipped detector, the one
    ``calibrate`` needs (the session's x flipped first, as its error on a mirrored session says)."""
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    args = (catalogue, maglim, use_engine, max_rounds, progress)
    result = _identify_iteratively(session, nominal, *args)
    if not result.mirrored:
        return result
    width = nominal.image_size_px[0]
    flipped = _identify_iteratively(_flipped_x_session(session, width), flipped_x_camera(nominal), *args)
    if flipped.mirrored is not False or flipped.n_identified < result.n_identified:
        return result
    frames = tuple(f if f.mirrored is None else replace(f, mirrored=not f.mirrored) for f in flipped.frames)
    return replace(flipped, session=_flipped_x_session(flipped.session, width), frames=frames)


def _flipped_x_session(session: Session, width_px: int) -> Session:
    """``session`` with every column mirrored, x -> width - 1 - x (docs/camera-model.md: x = 0 is the first
    column's centre)."""
    return replace(session, x_px=(width_px - 1) - session.x_px)


def flipped_x_camera(camera: CameraParams) -> CameraParams:
    """The camera of the same detector read with x -> width - 1 - x: the principal point's column mirrored, and the
    distortion terms odd in x (docs/camera-model.md: with u -> -u, dx -> -dx and dy unchanged when g1 = s1 + p1 and
    g3 = 2 p1 change sign, so p1 and s1 do) negated."""
    x0, y0 = camera.principal_point_px
    d = camera.distortion
    return replace(
        camera,
        principal_point_px=((camera.image_size_px[0] - 1) - x0, y0),
        distortion=replace(d, p1=-d.p1, s1=-d.s1),
    )


def _identify_iteratively(
    session: Session,
    nominal: CameraParams,
    catalogue: Catalogue | None = None,
    maglim: float | None = None,
    use_engine: bool = True,
    max_rounds: int = MAX_ROUNDS,
    progress=None,
) -> Identification:
    """Identify, calibrate, identify again with the calibrated camera, until a round adds nothing (at most
    ``max_rounds``; 1: :func:`identify_session` alone). Every round identifies the session's originally
    unidentified rows afresh (lost in space: the module docstring's checks apply in every round) with the camera
    the round before calibrated (:func:`hostlink.calibration.run.calibrate_session`, default method and
    parameters, the session's time or J2000 directions); the field edge, where an uncalibrated model errs most, is
    where the new stars are. A round is kept only when it identifies more stars than the one before; a calibration
    that fails (:meth:`CalibrationOutcome.failure`) ends the rounds. The result's ``rounds`` hold, per round: the
    camera used (focal length [px], where it came from), frames and stars identified, and the stars it added, lost
    and renamed against the round before."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.errors import UserError

    if max_rounds < 1:
        raise UserError(f"rounds must be at least 1, got {max_rounds}")
    if catalogue is None:
        from hostlink.sky.catalogue import load_catalogue

        catalogue = load_catalogue()
    if np.any(guided.candidate_rows(session)):  # faint candidates: held back, admitted after the rounds (guided.py)
        return guided.identify_then_admit(
            session, lambda s: _identify_iteratively(s, nominal, catalogue, maglim, use_engine, max_rounds, progress)
        )
    width = nominal.image_size_px[0]
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, width)

    def one_round(camera: CameraParams) -> Identification:
        return identify_session(session, camera, catalogue, maglim, use_engine, progress, database_fov_deg=fov)

    result = one_round(nominal)
    new = session.star_id == 0
    rounds = [_round_record(1, "nominal", nominal, result, np.zeros_like(session.star_id), new)]
    camera = nominal
    for number in range(2, max_rounds + 1):
        if result.n_frames_identified == 0:
            break
        try:
            outcome, _ = calibrate_session(result.session, camera, keep_failed=True)
        except UserError as exc:
            rounds[-1]["calibration"] = f"failed: {exc}"
            break
        failure = outcome.failure()
        rounds[-1]["calibration"] = failure or f"residual {outcome.after.get('rms_px', math.nan):.3f} px"
        if failure:
            break
        trial = one_round(outcome.params)
        record = _round_record(
            number, f"calibrated in round {number - 1}", outcome.params, trial, result.session.star_id, new
        )
        rounds.append(record)
        if trial.n_identified <= result.n_identified:
            record["kept"] = False  # nothing new: the round before stands
            break
        result, camera = trial, outcome.params
    return replace(result, rounds=tuple(rounds), camera=camera)


def _round_record(
    number: int, source: str, camera: CameraParams, result: Identification, before: np.ndarray, new: np.ndarray
) -> dict:
    """One round's report (:func:`identify_iteratively`): over the rows the session left unidentified (``new``), the
    stars this round identified, added (unidentified the round before), lost and renamed against ``before``."""
    now = result.session.star_id
    return {
        "round": number,
        "camera": source,
        "focal_length_px": float(camera.focal_length_px),
        "frames_identified": result.n_frames_identified,
        "stars_identified": int(np.count_nonzero(new & (now != 0))),
        "added": int(np.count_nonzero(new & (now != 0) & (before == 0))),
        "lost": int(np.count_nonzero(new & (now == 0) & (before != 0))),
        "renamed": int(np.count_nonzero(new & (now != 0) & (before != 0) & (now != before))),
        "kept": True,
    }
