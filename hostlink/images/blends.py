"""Unresolved pairs (issue 30): which catalogue star a detection can be when a second one lies beside it, and where
the light of a named detection comes from.

A detection is the light of every catalogue star within :data:`UNRESOLVED_PX` of it (two such stars make one peak
on the detector). Its calibrated magnitude M is its instrumental one plus the frame's photometric zero point (the
median of catalogue minus instrumental magnitude over the frame's identified unsaturated stars, scatter s: 1.4826
x their median absolute deviation, :func:`zero_point`); the photometric window is w = max(:data:`PHOTOMETRIC_SIGMAS`
x s, :data:`MIN_PHOTOMETRIC_WINDOW_MAG`) (:func:`window_mag`).

1. Who it can be (:func:`could_be`): a catalogue star could be the detection by itself when its light can explain
   the measured flux, its magnitude no fainter than M + w; a fainter one contributes, but cannot be the detection.
   A detection that two catalogue stars could each be stays unidentified (issue 30); when only one can, the
   detection IS that star, or the blend of it with its fainter companions, and is named after it.
2. Where its light comes from (:func:`blend_references`, :func:`photocentre`): the reference direction of a
   detection so named is where a centroid of the blend is expected, between the named star and the flux-weighted
   photocentre (the catalogue fluxes 10^(-0.4 Hp)) of it and every catalogue star within :data:`UNRESOLVED_PX` of it
   that the frame does not hold as a row of its own (a companion the detector resolved is its own detection). A
   centroid fitted with the PSF's width moves toward a companion at separation d by q d exp(-d^2 / (4 sigma_psf^2))
   (to first order in the flux ratio q: the least-squares centre of one Gaussian fitted to two), the photocentre's
   q d / (1 + q) when d is well inside the PSF; with sigma_psf from :data:`SHARPEST_PSF_SIGMA_PX` up, the factor
   lies between exp(-d^2 / (4 x 0.77^2)) and 1, and the reference takes the middle. Its ``sigma_px`` is the
   centroid's own (Cramer-Rao) part, without the bias bound ``centroid`` added for an elongated star (its
   ``blend_px`` column: the shift the reference models), grown in quadrature by that interval's spread (its length
   over sqrt(12)) and by the flux ratio's uncertainty (each companion's magnitude difference uncertain by
   sigma_dm = sqrt(2) x max(s, w / :data:`PHOTOMETRIC_SIGMAS`): the two stars' colour terms against the camera's
   band, independent; the reference's shift at -+ :data:`FLUX_RATIO_SIGMAS` sigma_dm over that many, not its
   derivative: :func:`_flux_ratio_px`). Checked against a least-squares PSF fit of rendered pairs
   (tests/test_images_blends.py): the fitted centre lies within sqrt(3) sigmas of the reference for PSF sigmas of
   0.77-3 px, separations to 3 px and flux ratios to 1.

The frames' rows keep their identities otherwise; a session without ``ra_deg``/``dec_deg`` columns gets them for
every identified row (the catalogue's place, as :func:`hostlink.images.skyindex._with_identities` writes them) when
one of its rows is a blend, since the reference service takes a file's columns for every row or for none
(:func:`hostlink.sky.references.geocentric_references`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from hostlink.files.session import Session, pixel_sigma_text, session_flag, session_number
from hostlink.sky.catalogue import Catalogue
from onboard.camera import radec_to_unit, unit_to_radec

if TYPE_CHECKING:
    from hostlink.images.skyindex import SkyIndex

#: Two stars nearer than this [px] are one detection: the sum of two equal Gaussians of sigma s has a single peak
#: below a separation of 2 s, and 3 px is 2 s for PSFs up to 1.5 px (the real sets' PSF widths: docs/realsky.md,
#: "Unresolved pairs"). Close doubles: 16 Cyg A and B, 40" apart, are half a pixel at 78" per pixel.
UNRESOLVED_PX = 3.0
#: Photometric agreement: within this many of the frame's zero-point scatters ...
PHOTOMETRIC_SIGMAS = 3.0
#: ... and never narrower than this [mag] (a zero point from few stars; Hipparcos Hp against an unfiltered detector's
#: band differs by colour, a few tenths of a magnitude).
MIN_PHOTOMETRIC_WINDOW_MAG = 0.75
#: The normal distribution's sigma over its median absolute deviation (a robust scatter of the zero point).
MAD_TO_SIGMA = 1.4826
#: The sharpest PSF a star camera of the real sets has [px, Gaussian sigma] (a 35 mm lens on 6.9 um pixels;
#: docs/realsky.md, "Unresolved pairs"): the lower bound of the centroid's response to an unresolved companion
#: (module docstring).
SHARPEST_PSF_SIGMA_PX = 0.77
#: How many sigmas of a companion's magnitude difference the flux ratio's term of a blend's sigma is taken at (the
#: excursion of the reference there, over this): the reference moves with the flux ratio 10^(-0.4 dm), skewed in a
#: magnitude error that is Gaussian, so that its excursion at 3 sigmas is up to 4.3 times the one at 1 sigma (a faint
#: companion, sigma_dm 0.35 mag) and a sigma from 1 sigma's excursion leaves too many errors beyond 3 sigmas
#: (docs/realsky.md, "Unresolved pairs").
FLUX_RATIO_SIGMAS = 3.0


def zero_point(catalogue_mag: np.ndarray, instrumental_mag: np.ndarray) -> tuple[float, float]:
    """(zero point, scatter) [mag] of a frame's identified stars: the median of catalogue minus instrumental
    magnitude and :data:`MAD_TO_SIGMA` x the median absolute deviation about it (NaN, NaN without finite ones)."""
    offsets = np.asarray(catalogue_mag, dtype=np.float64) - np.asarray(instrumental_mag, dtype=np.float64)
    offsets = offsets[np.isfinite(offsets)]
    if offsets.size == 0:
        return math.nan, math.nan
    zp = float(np.median(offsets))
    return zp, MAD_TO_SIGMA * float(np.median(np.abs(offsets - zp)))


def window_mag(scatter_mag: float) -> float:
    """The photometric window w [mag] of a frame whose zero point scatters by ``scatter_mag`` (module docstring)."""
    if not math.isfinite(scatter_mag):
        return MIN_PHOTOMETRIC_WINDOW_MAG
    return max(PHOTOMETRIC_SIGMAS * scatter_mag, MIN_PHOTOMETRIC_WINDOW_MAG)


def could_be(star_mag: np.ndarray, detection_mag: np.ndarray, window: float) -> np.ndarray:
    """Whether catalogue stars of magnitude ``star_mag`` could each be, by themselves, detections of calibrated
    magnitude ``detection_mag`` (instrumental plus the frame's zero point; broadcast): no fainter than it by more than
    ``window`` [mag]. An unknown (NaN) magnitude gives False: the caller decides what an unknown magnitude means."""
    with np.errstate(invalid="ignore"):
        return np.asarray(star_mag) <= np.asarray(detection_mag) + window


@dataclass(frozen=True)
class Photocentre:
    """Where a named star's detection is expected when unresolved companions add their light: the reference unit
    vector (3,), its 1-sigma per axis [px] (flux ratio and centroid response, module docstring), its offset from the
    named star [px], the flux-weighted photocentre's offset [px] and the companions' Hipparcos numbers."""

    direction: np.ndarray
    sigma_px: float
    offset_px: float
    photocentre_offset_px: float
    companions: tuple[int, ...]


def photocentre(
    r_star: np.ndarray,
    mag_star: float,
    r_companions: np.ndarray,
    mag_companions: np.ndarray,
    focal_px: float,
    scatter_mag: float,
    hip_companions: tuple[int, ...] = (),
) -> Photocentre:
    """The reference of a star (unit vector ``r_star``, magnitude ``mag_star``) blended with its companions ((K, 3),
    (K,)) at ``focal_px`` for a frame whose zero point scatters by ``scatter_mag`` (module docstring). The centroid
    moves toward companion k by q_k g_k d_k / (1 + sum q g) (q_k its flux ratio to the star, d_k its offset [px],
    g_k = exp(-d_k^2 / (4 sigma_psf^2)) the response of a centroid fitted with the PSF's width, 1 for the
    photocentre): g_k lies between its value at :data:`SHARPEST_PSF_SIGMA_PX` and 1, and the reference takes the
    middle, g_k = (1 + g_min) / 2, with that interval's spread (its length over sqrt(12)) and the flux ratio's
    (:func:`_flux_ratio_px`) in quadrature as its 1-sigma. For separations well inside the PSF (g_min near 1) it is
    the photocentre. Offsets on the tangent plane: d_k = (r_k - r_star) focal_px (a few px, where the tangent plane
    and the sphere differ by parts in 10^7)."""
    q = 10.0 ** (-0.4 * (np.asarray(mag_companions, dtype=np.float64) - mag_star))  # flux ratios to the star
    d = (r_companions - r_star) * focal_px  # (K, 3) px, nearly in the tangent plane
    g_min = np.exp(-np.sum(d**2, axis=1) / (4.0 * SHARPEST_PSF_SIGMA_PX**2))
    w = q * 0.5 * (1.0 + g_min)  # the companions' weights at the middle of their response
    total = 1.0 + float(np.sum(w))
    direction = (r_star + w @ r_companions) / total
    direction = direction / np.linalg.norm(direction)
    u = w @ d / total  # the reference's offset from the star [px]
    sigma_dm = math.sqrt(2.0) * max(
        scatter_mag if math.isfinite(scatter_mag) else 0.0, window_mag(scatter_mag) / PHOTOMETRIC_SIGMAS
    )
    ratio_px = _flux_ratio_px(q, 0.5 * (1.0 + g_min), d, sigma_dm)
    spread_px = float(np.linalg.norm((q * (1.0 - g_min)) @ d)) / total / math.sqrt(12.0)
    photo_px = float(np.linalg.norm(q @ d)) / (1.0 + float(np.sum(q)))
    return Photocentre(
        direction, math.hypot(ratio_px, spread_px), float(np.linalg.norm(u)), photo_px, tuple(hip_companions)
    )


def _flux_ratio_px(q: np.ndarray, g: np.ndarray, d_px: np.ndarray, sigma_dm: float) -> float:
    """The flux ratios' term of a blend reference's 1-sigma [px]: for each companion (flux ratio ``q`` (K,), response
    ``g`` (K,), offset ``d_px`` (K, 3)) the larger shift of the reference offset sum_k q_k g_k d_k / (1 + sum q g)
    when its magnitude difference moves by -+ :data:`FLUX_RATIO_SIGMAS` x ``sigma_dm``, over
    :data:`FLUX_RATIO_SIGMAS`; the companions (independent) in quadrature. The shift itself, not its derivative: the
    flux ratio is skewed where its magnitude error is Gaussian (module docstring)."""

    def offset(w: np.ndarray) -> np.ndarray:
        return w @ d_px / (1.0 + float(np.sum(w)))

    u = offset(q * g)
    total = 0.0
    for k in range(q.size):
        shifts = []
        for sign in (-1.0, 1.0):
            w = q * g
            w[k] *= 10.0 ** (0.4 * sign * FLUX_RATIO_SIGMAS * sigma_dm)
            shifts.append(float(np.linalg.norm(offset(w) - u)))
        total += max(shifts) ** 2
    return math.sqrt(total) / FLUX_RATIO_SIGMAS


def blend_references(
    session: Session, before: np.ndarray, catalogue: Catalogue, focal_px: float, index: SkyIndex | None = None
) -> tuple[Session, list[dict]]:
    """``session`` (its ``star_id`` final) with every row identified here (``before`` == 0, the ``star_id`` the rows
    had before identification) that has unresolved catalogue companions given the photocentre as its ``ra_deg``/
    ``dec_deg`` and its ``sigma_px`` grown in quadrature (module docstring), and one record per such row (frame,
    row, hip, companions, offset_px, sigma_px). Returns the session unchanged (and no record) when no row is a
    blend. ``index``: the :class:`hostlink.images.skyindex.SkyIndex` of ``catalogue`` when the caller holds one."""
    from hostlink.sky.apparent import hip_find

    new = np.flatnonzero((session.star_id != 0) & (before == 0))
    cat_rows, found = hip_find(catalogue, session.star_id[new])
    new, cat_rows = new[found], cat_rows[found]
    if new.size == 0:
        return session, []
    from hostlink.images.skyindex import sky_index

    index = sky_index(catalogue, index)
    r_all, tree = index.directions, index.tree
    found = tree.query_ball_point(r_all[cat_rows], 2.0 * math.sin(0.5 * UNRESOLVED_PX / focal_px))
    frame_of_row = np.repeat(np.arange(session.n_frames), np.diff(session.frame_starts))
    blends = []
    for row, own, near in zip(new, cat_rows, found, strict=True):
        if len(near) < 2:
            continue  # only itself
        near = np.asarray([c for c in near if c != own], dtype=np.int64)
        k = int(frame_of_row[row])
        a, b = int(session.frame_starts[k]), int(session.frame_starts[k + 1])
        near = near[~np.isin(catalogue.hip[near], session.star_id[a:b])]  # resolved: a row of its own
        if near.size:
            blends.append((int(row), int(own), np.sort(near), k))
    if not blends:
        return session, []
    return _with_photocentres(session, catalogue, blends, focal_px)


def _frame_scatter(session: Session, catalogue: Catalogue, mag: np.ndarray, frame: int) -> float:
    """The zero point's scatter [mag] of the session's ``frame``-th frame (its identified unsaturated stars)."""
    from hostlink.sky.apparent import hip_find

    a, b = int(session.frame_starts[frame]), int(session.frame_starts[frame + 1])
    saturated = session_flag(session, "saturated")[a:b]
    named = a + np.flatnonzero((session.star_id[a:b] != 0) & ~saturated)
    known, found = hip_find(catalogue, session.star_id[named])
    return zero_point(catalogue.mag[known[found]], mag[named[found]])[1]


def _with_photocentres(session, catalogue, blends, focal_px) -> tuple[Session, list[dict]]:
    """:func:`blend_references` for the rows ``blends`` ((row, catalogue row, companion rows, frame index))."""
    from hostlink.images.skyindex import catalogue_radec_deg

    ra, dec = _reference_columns(session, catalogue)
    sigma = without_pair_bound(session_number(session, "sigma_px"), session_number(session, "blend_px"))
    mag = session.mag if session.mag is not None else np.full(len(session), np.nan)
    # the members' places as the reference service sees them (apparent at the frame's time, or J2000), in one call
    members = [np.concatenate([[own], near]) for _, own, near, _ in blends]
    at_row = np.concatenate([np.full(m.size, row) for m, (row, *_) in zip(members, blends, strict=True)])
    ra_m, dec_m = catalogue_radec_deg(session, catalogue, np.concatenate(members), at_row)
    r_m = radec_to_unit(np.radians(ra_m), np.radians(dec_m))
    scatter = {k: _frame_scatter(session, catalogue, mag, k) for k in sorted({k for *_, k in blends})}
    records, first = [], 0
    for (row, own, near, k), m in zip(blends, members, strict=True):
        r = r_m[first : first + m.size]
        first += m.size
        hips = tuple(int(h) for h in catalogue.hip[near])
        pc = photocentre(r[0], float(catalogue.mag[own]), r[1:], catalogue.mag[near], focal_px, scatter[k], hips)
        ra_rad, dec_rad = unit_to_radec(pc.direction[None, :])
        ra[row], dec[row] = float(np.degrees(ra_rad[0])), float(np.degrees(dec_rad[0]))
        if math.isfinite(sigma[row]):
            sigma[row] = math.hypot(sigma[row], pc.sigma_px)
        records.append(
            {
                "frame": int(session.frame[row]),
                "row": int(row),
                "hip": int(catalogue.hip[own]),
                "companions": list(pc.companions),
                "offset_px": pc.offset_px,
                "photocentre_offset_px": pc.photocentre_offset_px,
                "sigma_px": pc.sigma_px,
                "focal_px": float(focal_px),
            }
        )
    extra = dict(session.extra)
    if "sigma_px" in extra:
        column = extra["sigma_px"].copy()  # the other rows' text as it was
        rows = [rec["row"] for rec in records]
        for row, text in zip(rows, pixel_sigma_text(sigma[rows]), strict=True):
            column[row] = text or column[row]  # no value: the text as it was
        extra["sigma_px"] = column
    if "blend_px" in extra:  # the bound a reference replaced is no longer in sigma_px: the column says what is
        column = extra["blend_px"].copy()
        for rec in records:
            if np.isfinite(sigma[rec["row"]]):
                column[rec["row"]] = ""
        extra["blend_px"] = column
    return replace(session, ra_deg=ra, dec_deg=dec, extra=extra), records


def without_pair_bound(sigma_px: np.ndarray, blend_px: np.ndarray) -> np.ndarray:
    """The rows' ``sigma_px`` without the bias bound b = ``blend_px`` of an unresolved companion that ``centroid``
    added to it as sqrt(sigma^2 + b^2 / 2) (:func:`hostlink.images.centroid.frame._measured`): the blend reference
    models that shift, and its own sigma replaces the bound. Rows without the column (an older session) or without
    a bound (NaN) keep theirs; a difference below 0 (both columns rounded to 4 digits) is 0."""
    b = np.where(np.isfinite(blend_px), blend_px, 0.0)
    return np.sqrt(np.maximum(sigma_px**2 - 0.5 * b**2, 0.0))


def _reference_columns(session: Session, catalogue: Catalogue) -> tuple[np.ndarray, np.ndarray]:
    """Copies of the session's ra_deg/dec_deg, or new ones with every identified row's catalogue place."""
    if session.ra_deg is not None and session.dec_deg is not None:
        return session.ra_deg.copy(), session.dec_deg.copy()
    from hostlink.images.skyindex import catalogue_radec_deg
    from hostlink.sky.apparent import hip_find

    ra, dec = np.full(len(session), np.nan), np.full(len(session), np.nan)
    rows = np.flatnonzero(session.star_id != 0)
    known, found = hip_find(catalogue, session.star_id[rows])
    rows, known = rows[found], known[found]
    if rows.size:
        ra[rows], dec[rows] = catalogue_radec_deg(session, catalogue, known, rows)
    return ra, dec
