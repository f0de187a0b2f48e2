"""One frame's identification (:mod:`hostlink.images.identify`, module docstring): the engine's or the own matcher's
proposals (:func:`identify_frame`), each verified, extended and verified again (:func:`_confirm`) into a
:class:`FrameIdentity`."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from hostlink.calibration.model import ARCSEC_PER_RAD
from hostlink.images import solver_adapter
from hostlink.images.extend import (
    EXTEND_MAG_MARGIN,
    _ambiguous,
    _calibrated_mag,
    _completeness,
    _extend,
    _faintest_detectable,
    _radial_search_by_hits,
    _too_faint,
    _zero_point,
)
from hostlink.images.matcher import (
    ANCHOR_REL_TOL,
    ANCHOR_REL_TOL_KNOWN,
    ANCHOR_STARS,
    DEEP_ANCHOR_STARS,
    DEEP_MATCH_STARS,
    MATCH_STARS,
    MAX_ANCHOR_PAIRS,
    _anchor_schedule,
    anchor_candidates,
)
from hostlink.images.skyindex import PairCatalogue, _Sky
from hostlink.images.verify import PARITY_MIN_AGREEMENT, _absolute_scale, _verify, _verify_best_parity
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams

#: Brightest-centroid subsets the engine is tried on after the whole frame (the engine's, for its calibration too).
ENGINE_SUBSETS = solver_adapter.ENGINE_SUBSETS


#: A frame's identification is accepted with at least this many verified stars (4 stars give 5 independent
#: interstar angles beyond the attitude: a chance alignment of 4 wrong identities within the tolerance is
#: negligible, and the engine's own false-match probability budget is 1e-5).
MIN_VERIFIED = 4


#: ... and when the verified stars are at least this fraction of the frame's candidates.
MIN_VERIFIED_FRACTION = 0.6


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
#: ... and at most this many extension rounds in all (above).
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


def _boresight_and_roll(c: np.ndarray) -> tuple[float, float, float]:
    """Boresight (ra, dec) [deg] and roll [deg]: the angle from the image's -y axis (up) to the celestial north
    projected into the image, measured toward +x (the one formula: :func:`hostlink.sky.pointing.boresight_radec_roll`,
    which ``hostlink attitude`` writes too)."""
    from hostlink.sky.pointing import boresight_radec_roll

    return boresight_radec_roll(c)


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
    scanned: bool = False,
) -> tuple[FrameIdentity, np.ndarray]:
    """Verify, extend and verify again a proposal (module docstring, steps 2-4): the frame's identity and the
    (N,) Hipparcos number of each centroid (0 where not identified). ``scale``: F / F_nominal when known (a
    matcher's proposal, whose wrong pairs are then pruned), else estimated from the proposal. ``mag``: the
    centroids' instrumental magnitudes, when known: candidates far too faint for them are dropped
    (:func:`_too_faint`) and the extension goes no deeper than the frame's faintest centroid implies."""
    hip_out = np.zeros(x_px.shape[0], dtype=np.int64)
    n_proposed = int(rows.size)
    r_corner = 0.5 * math.hypot(*image_size_px)
    v = _verify_best_parity(
        x_px[rows], y_px[rows], sky.r[stars], theta, mirrored_hint, scale, scale is not None, r_corner
    )
    if v.attitude is None:
        return replace(ident, n_candidates=n_proposed, status="not verified"), hip_out
    if scale is not None:  # a matcher's few stars verify through any k1: the lens searched over the frame
        mag_limit = float(np.max(sky.mag[stars[v.keep]])) + EXTEND_MAG_MARGIN
        searched = _radial_search_by_hits(x_px, y_px, rows, stars, v, sky, image_size_px, mag_limit, scanned)
        if searched is not v and scanned:
            scale = None  # the scan's step was the nominal lens's scale at the anchors, the lens found's is not it
        v = searched
    extended = _extension_rounds(x_px, y_px, rows, stars, v, theta, sky, image_size_px, mag)
    if extended is None:
        return replace(ident, n_candidates=n_proposed, status="not verified"), hip_out
    rows, stars, v, mag_limit = extended
    v = replace(v, keep=v.keep & ~_too_faint(mag, rows, stars, sky, _zero_point(mag, rows[v.keep], stars[v.keep], sky)))
    ambiguous = v.keep & _ambiguous(
        x_px[rows],
        y_px[rows],
        stars,
        sky,
        theta,
        v,
        image_size_px,
        mag_limit,
        *_calibrated_mag(mag, rows, rows, stars, v, sky),
    )
    v = replace(v, keep=v.keep & ~ambiguous)
    ident = replace(
        ident,
        n_candidates=max(n_proposed, int(rows.size)),
        mirrored=v.mirrored,
        scale=_absolute_scale(v, theta),
        n_ambiguous=int(np.count_nonzero(ambiguous)),
    )
    refused = _refusal(ident, v, rows, stars, theta, sky, image_size_px, x_px, y_px, scale)
    if refused:
        return replace(ident, status=refused), hip_out
    hip_out[rows[v.keep]] = sky.hip[stars[v.keep]]
    ra, dec, roll = _boresight_and_roll(v.attitude)
    rms = float(np.sqrt(np.mean(v.residual_rad[v.keep] ** 2))) * ARCSEC_PER_RAD
    identified = replace(
        ident,
        n_identified=int(np.count_nonzero(v.keep)),
        status="identified",
        attitude=v.attitude,
        ra_deg=ra,
        dec_deg=dec,
        roll_deg=roll,
        residual_arcsec=rms,
    )
    return identified, hip_out


def _extension_rounds(x_px, y_px, rows, stars, v, theta, sky, image_size_px, mag):
    """The extension rounds of :func:`_confirm` (module docstring, step 3): (rows, stars, verification, the depth
    reached [mag]), or None when a round's verification fails."""
    n = x_px.shape[0]
    r_corner = 0.5 * math.hypot(*image_size_px)
    mag_limit = float(np.max(sky.mag[stars[v.keep]])) + EXTEND_MAG_MARGIN
    theta_frame = theta  # the camera later rounds verify through: the frame's own once refined
    for round_no in range(MAX_EXTEND_ROUNDS):
        taken = np.zeros(n, dtype=bool)
        taken[rows[v.keep]] = True
        zero_point = _zero_point(mag, rows[v.keep], stars[v.keep], sky)
        mag_limit = min(mag_limit, _faintest_detectable(mag, zero_point))
        calibrated_mag, window = _calibrated_mag(mag, np.arange(n), rows, stars, v, sky)
        new_rows, new_stars = _extend(
            x_px, y_px, sky, theta, v, taken, mag_limit, image_size_px, calibrated_mag, window
        )
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
            return None
        # deeper as the verified stars go deeper (a proposal of bright stars alone reaches the frame's faint ones)
        mag_limit = max(mag_limit, float(np.max(sky.mag[stars[v.keep]])) + EXTEND_MAG_MARGIN)
    return rows, stars, v, mag_limit


def _refusal(ident, v, rows, stars, theta, sky, image_size_px, x_px, y_px, scale) -> str | None:
    """Why :func:`_confirm` refuses a verified and extended proposal (module docstring, step 4), None to accept."""
    n_ok = int(np.count_nonzero(v.keep))
    if n_ok < MIN_VERIFIED:
        return f"only {n_ok} stars verified (need {MIN_VERIFIED})"
    if n_ok < MIN_VERIFIED_FRACTION * rows.size:
        return f"only {n_ok} of {rows.size} candidates verified"
    if not v.parity_agreement >= PARITY_MIN_AGREEMENT:
        return "parity not unanimous"
    completeness = _completeness(sky, theta, v, image_size_px, stars[v.keep], x_px, y_px)
    if completeness < MIN_COMPLETENESS:
        return f"only {100 * completeness:.0f} % of the bright stars in the field found"
    if scale is not None and abs(ident.scale / scale - 1.0) > SCALE_AGREEMENT:
        return f"scale {ident.scale:.4f} disagrees with the session's {scale:.4f}"
    return None


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
                    ident,
                    x_px,
                    y_px,
                    bright[rows],
                    stars,
                    mirrored,
                    theta,
                    sky,
                    nominal.image_size_px,
                    scale,
                    mag,
                    scanned=not known,
                )
                if result[0].status == "identified":
                    return result
                if result[0].n_candidates > best[0].n_candidates:
                    best = result
            if cut:
                status = f"no match within {MAX_ANCHOR_PAIRS} anchor pairs"
                return replace(best[0], status=f"{status} ({best[0].status})"), best[1]
    return best
