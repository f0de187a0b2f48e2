"""Blends: a star's shape against the PSF of its part of the field, and the bound on a blend's centroid bias from
its shape or its neighbours' light (:mod:`hostlink.images.centroid`, step 3)."""

from __future__ import annotations

import math

import numpy as np

from hostlink.images.centroid.psf import _psf_shape_batch
from hostlink.images.centroid.stamps import _in_chunks, _stamps
from hostlink.images.centroid.windows import _WINPOS_MAX_SHIFT_PX, _symmetric_window

#: An ellipticity is significant beyond this many standard deviations of its noise (a round star exceeds it with
#: probability exp(-16 / 2) = 3e-4: the ellipticity's two components are Gaussian with that deviation).
_ELLIPTICITY_SIGNIFICANCE = 4.0


#: Well-measured stars needed to take the frame's PSF shape from them (else the PSF is taken as round).
_PSF_SHAPE_STARS = 5


#: ... whose ellipticity is known to this standard deviation.
_PSF_SHAPE_MAX_SIGMA = 0.1


#: A blend (a deblended star beside a neighbour, or one more elongated than the PSF of its part of the field) is kept,
#: flagged, while the bound on its centroid's bias is at most this [px]: the shift beyond which a windowed centroid
#: has failed (:data:`_WINPOS_MAX_SHIFT_PX`); the bound enters its ``sigma_px`` (:func:`_measured`), so the
#: calibration's weights and outlier gate judge it, not the extractor.
_BLEND_MAX_BIAS_PX = _WINPOS_MAX_SHIFT_PX


def _neighbour_bias_px(objects: np.ndarray, which: np.ndarray, sigma_px: float) -> np.ndarray:
    """(N,) bound [px] on the centroid bias that the detected neighbours' light causes, for the objects ``which``
    (NaN for the others): |sum_j (F_j / F) (r_j - r) exp(-|r_j - r|^2 / (4 sigma^2))| over the other detections j,
    F the isophotal fluxes. For a Gaussian PSF of ``sigma_px`` and a Gaussian window of the same sigma, the windowed
    centroid's fixed point moves by exactly that much per neighbour to first order (the window times the
    neighbour's PSF is a Gaussian centred half way, of half the variance); the least-squares PSF fit over the whole
    star moves by the same amount (its cross term is the derivative of the PSF's autocorrelation, a Gaussian of
    variance 2 sigma^2). A saturated star's isophotal flux is a lower bound: its bound is an upper one."""
    out = np.full(objects.size, np.nan)
    rows = np.flatnonzero(which)
    if rows.size == 0:
        return out
    x, y = objects["x"].astype(np.float64), objects["y"].astype(np.float64)
    flux = objects["flux"].astype(np.float64)
    dx, dy = x[None, :] - x[rows, None], y[None, :] - y[rows, None]
    weight = np.exp(-(dx**2 + dy**2) / (4.0 * sigma_px**2)) * np.maximum(flux, 0.0)[None, :]
    weight[np.arange(rows.size), rows] = 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        bias = np.hypot(np.sum(weight * dx, axis=1), np.sum(weight * dy, axis=1)) / flux[rows]
    out[rows] = np.where(flux[rows] > 0, bias, np.inf)
    return out


def _shape_bias_px(excess: np.ndarray, size_px2: np.ndarray) -> np.ndarray:
    """Bound [px] on the centroid bias of a star whose windowed ellipticity exceeds the PSF's by ``excess`` (the
    modulus of the difference), its windowed second moments summing to ``size_px2`` [px^2]: 2 sqrt(excess x size).
    The excess second moment along the major axis is excess x size in the window of the PSF's sigma, 4 times that
    unwindowed (a Gaussian star windowed by a Gaussian of its own sigma: d(windowed variance) / d(variance) = 1/4);
    a companion of flux share q at distance d adds q (1 - q) d^2 to it and moves the light's centroid by q d from
    the brighter star, at most sqrt(q (1 - q)) d for q <= 1/2: the square root bounds the shift."""
    with np.errstate(invalid="ignore"):
        return 2.0 * np.sqrt(np.maximum(excess, 0.0) * np.maximum(size_px2, 0.0))


#: A deblended detection is measured as a single star when every other detection lies farther than this many PSF
#: sigmas: a neighbour of flux ratio q at d = 6 sigma moves the PSF fit by q d exp(-d^2 / (4 sigma^2)) =
#: 7.4e-4 q sigma [px] (:func:`_neighbour_bias_px`; the package's fit of a rendered pair moved 0.015 px for q = 10
#: at sigma 1.5 px). Its light at the fit stamp's edge (3 sigma + 1 px from the star) is not small, 13 % of its peak
#: at sigma 1 px: the shift, not that light, is what makes the star a single one.
_BLEND_CLEAR_SIGMAS = 6.0


def _nearest_neighbour_px(x: np.ndarray, y: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Distance [px] from each detection selected by ``which`` to its nearest other detection (inf where none; 0 for
    the detections not selected)."""
    out = np.zeros(x.size)
    rows = np.flatnonzero(which)
    if rows.size:
        d = np.hypot(x[rows, None] - x[None, :], y[rows, None] - y[None, :])
        d[np.arange(rows.size), rows] = np.inf
        out[rows] = d.min(axis=1) if x.size > 1 else np.inf
    return out


def _unresolved_pairs(
    e: np.ndarray,
    e_sigma: np.ndarray,
    max_ellipticity: float,
    x_px: np.ndarray | None = None,
    y_px: np.ndarray | None = None,
    shape_px: tuple[int, int] | None = None,
    usable: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Stars more elongated than the frame's PSF where they are: |e - e_psf(x, y)| beyond ``max_ellipticity`` and
    beyond :data:`_ELLIPTICITY_SIGNIFICANCE` x sqrt(spread^2 + noise^2) (the spread of the stars' ellipticities about
    the model beyond their noise, which also holds what the noise estimate misses, e.g. correlated pixels: a single
    star exceeds it with probability exp(-16 / 2) = 3e-4). ``e_psf`` is :func:`_psf_ellipticity_field`, fitted to
    every star whose ellipticity is known to :data:`_PSF_SHAPE_MAX_SIGMA` (blends are a minority; ``usable``: the
    stars that may serve, None: all; a deblended star kept beside its neighbour does not): a real lens's PSF is
    elliptical (coma, astigmatism, an undersampled spot on the pixel grid) by 0.1-0.3 and, in a wide field, changes
    across it (elongated radially towards the edge: on the 27-deg granasat frames e ~ 0.2-0.35 beyond 400 px from the
    centre, against ~0.05 at it). Only what stands out from the PSF of its own part of the field is a blend. Returns
    that (N,) bool and each star's |e - e_psf|."""
    reference = np.flatnonzero((e_sigma < _PSF_SHAPE_MAX_SIGMA) & (True if usable is None else usable))
    e_psf, spread = np.zeros_like(e), 0.0
    if reference.size >= _PSF_SHAPE_STARS:
        if x_px is None or y_px is None or shape_px is None:
            x_px, y_px, shape_px = np.zeros(e.shape[0]), np.zeros(e.shape[0]), (1, 1)
        e_psf, spread = _psf_ellipticity_field(e, e_sigma, x_px, y_px, shape_px, reference)
    deviation = np.hypot(*(e - e_psf).T)
    scatter = np.sqrt(spread**2 + e_sigma**2)  # per component: the PSF's own spread and the star's noise
    return (deviation > max_ellipticity) & (deviation > _ELLIPTICITY_SIGNIFICANCE * scatter), deviation


#: Reference stars per free coefficient before the PSF's ellipticity is modelled across the field (a quadratic in
#: x, y per component, 6 coefficients) rather than taken as the frame's median.
_PSF_FIELD_STARS_PER_TERM = 5


#: Rounds of the robust fit of the PSF's ellipticity across the field; a star is left out of the next round when its
#: deviation^2 / (spread^2 + noise^2) exceeds the chi-square (2 degrees of freedom) 99.73 % point (3 sigma).
_PSF_FIELD_ROUNDS = 4


_PSF_FIELD_CHI2 = -2.0 * math.log(1.0 - 0.9973)


def _psf_ellipticity_field(
    e: np.ndarray,
    e_sigma: np.ndarray,
    x_px: np.ndarray,
    y_px: np.ndarray,
    shape_px: tuple[int, int],
    reference: np.ndarray,
) -> tuple[np.ndarray, float]:
    """The PSF's ellipticity at every star (n, 2) and its spread per component about that model: the median of the
    ``reference`` stars when they are fewer than :data:`_PSF_FIELD_STARS_PER_TERM` x 6, else a quadratic in the
    field position per component (the lowest order that holds the radial elongation of astigmatism and field
    curvature, e1 ~ x^2 - y^2, e2 ~ 2 x y about the centre, and coma's linear term), fitted by least squares over
    the reference stars that agree with it (iterated, :data:`_PSF_FIELD_ROUNDS`, blends clipped). The spread is robust
    (a median over every reference star, blends a minority):
    |e - e_psf|^2 / v is chi-square with 2 degrees of freedom (median 2 ln 2) for a per-component variance
    v = spread^2 + noise^2: the PSF's own spread is what is left after the noise."""

    def spread_of(rows: np.ndarray, model: np.ndarray) -> float:
        # the s that makes the median of |e - e_psf|^2 / (s^2 + noise^2) that of a chi-square with 2 degrees of
        # freedom, 2 ln 2 (0 when the noise alone explains more than half of the deviations): bisection, the median
        # falls as s grows
        d2 = np.sum((e[rows] - model[rows]) ** 2, axis=1)
        v = e_sigma[rows] ** 2
        target = 2.0 * math.log(2.0)
        if float(np.median(d2 / np.maximum(v, 1e-30))) <= target:
            return 0.0
        lo, hi = 0.0, math.sqrt(float(np.max(d2)) / target)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if float(np.median(d2 / (mid**2 + v))) > target else (lo, mid)
        return hi

    model = np.broadcast_to(np.median(e[reference], axis=0), e.shape).copy()
    spread = spread_of(reference, model)
    if reference.size < 6 * _PSF_FIELD_STARS_PER_TERM:
        return model, spread
    height, width = shape_px
    scale = 0.5 * math.hypot(width, height)
    u = (np.asarray(x_px, np.float64) - 0.5 * (width - 1)) / scale
    v = (np.asarray(y_px, np.float64) - 0.5 * (height - 1)) / scale
    design = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    rows = None
    for _ in range(_PSF_FIELD_ROUNDS):
        # from the median's inliers (blends clustered in one part of the field are not absorbed), or from every
        # reference star when the median leaves too few (the PSF changes across the field more than it spreads)
        chi2 = np.sum((e[reference] - model[reference]) ** 2, axis=1) / (spread**2 + e_sigma[reference] ** 2)
        inliers = reference[chi2 <= _PSF_FIELD_CHI2]
        if inliers.size < 6 * _PSF_FIELD_STARS_PER_TERM:
            if rows is not None:
                break
            inliers = reference
        if rows is not None and np.array_equal(inliers, rows):
            break
        rows = inliers
        coef, *_ = np.linalg.lstsq(design[rows], e[rows], rcond=None)
        model = design @ coef
        spread = spread_of(reference, model)  # over all: a spread over the inliers alone shrinks round by round
    return model, spread


#: The second moments' stamp: +-this many window sigmas, rounded up (the window's weight there, exp(-8), is 3.4e-4 of
#: its peak).
_MOMENT_HALF_SIGMAS = 4


def _moment_half_px(sigma_px: float) -> int:
    """The half-width [px] of the second moments' stamp for a window of ``sigma_px`` (:data:`_MOMENT_HALF_SIGMAS`)."""
    return int(math.ceil(_MOMENT_HALF_SIGMAS * sigma_px))


def _windowed_ellipticity(
    sub: np.ndarray, rms: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float, gain_e_per_adu: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Ellipticity (Mxx - Myy, 2 Mxy) / (Mxx + Myy) (n, 2) of the Gaussian-weighted (window sigma = the PSF's) second
    moments M of each star around its centroid, and its standard deviation from the pixel noise (linear
    propagation: dM/dI_i = w_i (q_i - M) / sum w I; variance rms^2, plus the star's shot noise I / gain [ADU^2]
    when the gain is known). A round PSF gives 0; two equal stars d apart along x give Mxx - Myy ~ d^2 / 16 over
    Mxx + Myy ~ sigma^2 + d^2 / 16: 0.2 at d = 2 sigma, where no saddle separates them. Returns e, its standard
    deviation and Mxx + Myy [px^2] (NaN where the moments are not measured)."""
    if x.size == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    half = _moment_half_px(sigma_px)
    return _in_chunks(
        half, x.size, lambda k: _windowed_ellipticity_block(sub, rms, x[k], y[k], sigma_px, gain_e_per_adu, half)
    )


def _windowed_ellipticity_block(sub, rms, x, y, sigma_px: float, gain_e_per_adu: float | None, half: int):
    """:func:`_windowed_ellipticity` of one block of stars."""
    cols, rows, data, inside = _stamps(sub, x, y, half)
    var = _pixel_variance(rms, x, y, half, inside, data, gain_e_per_adu)
    dx = (cols - x[:, None])[:, None, :]
    dy = (rows - y[:, None])[:, :, None]
    weight = np.where(inside, np.exp(-(dx**2 + dy**2) / (2 * sigma_px**2)), 0.0)
    return _moment_ellipticity(weight, data, dx, dy, var)


def _pixel_variance(rms, x, y, half: int, inside, data, gain_e_per_adu: float | None) -> np.ndarray:
    """Each stamp pixel's noise variance [ADU^2]: the local noise squared, plus the signal's shot noise
    I / gain when the gain is known (0 outside the image)."""
    var = np.where(inside, _stamps(rms, x, y, half)[2], 0.0) ** 2
    if gain_e_per_adu:
        var = var + np.maximum(data, 0.0) / gain_e_per_adu
    return var


def _moment_ellipticity(weight, data, dx, dy, var):
    """Ellipticity (n, 2), its standard deviation (n,) and Mxx + Myy (n,) of the second moments of ``data``
    (n, H, W) weighted by ``weight`` about the stamp's origin offsets ``dx`` (n, 1, W), ``dy`` (n, H, 1)
    (:func:`_windowed_ellipticity`); ``var`` the pixels' noise variance."""
    e = np.zeros((data.shape[0], 2))
    e_sigma = np.full(data.shape[0], np.inf)
    wd = weight * data
    total = np.sum(wd, axis=(1, 2))
    qa, qb, qt = dx**2 - dy**2, 2 * dx * dy, dx**2 + dy**2
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.sum(wd * qa, axis=(1, 2)) / total
        b = np.sum(wd * qb, axis=(1, 2)) / total
        t = np.sum(wd * qt, axis=(1, 2)) / total
        ok = (total > 0) & (t > 0)
        wn = weight / total[:, None, None]
        var_a = np.sum(wn**2 * (qa - a[:, None, None]) ** 2 * var, axis=(1, 2))
        var_b = np.sum(wn**2 * (qb - b[:, None, None]) ** 2 * var, axis=(1, 2))
    e[ok] = np.column_stack([a / t, b / t])[ok]
    e_sigma[ok] = (np.sqrt(0.5 * (var_a + var_b)) / t)[ok]
    return e, e_sigma, np.where(ok, t, np.nan)


def _border_ellipticity(sub, rms, x, y, sigma_px: float, gain_e_per_adu: float | None):
    """:func:`_windowed_ellipticity` of stars the border cuts, over the region of :func:`_border_windows` (the part
    of the image point-symmetric about the star), less the ellipticity a round star of the frame's PSF sigma
    (:func:`hostlink.images.centroid.psf._psf_shape_batch`, at the same position) shows over that region: what is
    left is the star's own elongation, as for a whole star. Returns e, its standard deviation and Mxx + Myy
    over the region."""
    half = _moment_half_px(sigma_px)
    cols, rows, data, inside = _stamps(sub, x, y, half)
    var = _pixel_variance(rms, x, y, half, inside, data, gain_e_per_adu)
    h, w = sub.shape
    wx, wy, _ = _symmetric_window(cols, rows, x, y, sigma_px, w, h)
    weight = wy[:, :, None] * wx[:, None, :]
    dx = (cols - x[:, None])[:, None, :]
    dy = (rows - y[:, None])[:, :, None]
    e, e_sigma, size = _moment_ellipticity(weight, data, dx, dy, var)
    round_star = _psf_shape_batch(cols, rows, x, y, sigma_px)
    e_round, *_ = _moment_ellipticity(weight, round_star, dx, dy, np.zeros_like(var))
    return e - e_round, e_sigma, size
