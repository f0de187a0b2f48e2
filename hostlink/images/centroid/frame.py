"""One image, stage by stage: extraction and screening, centroids, blends, the PSF fit, fluxes and ``sigma_px``
(:mod:`hostlink.images.centroid`, steps 1-6)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from hostlink.images.background import saturated_regions
from hostlink.images.centroid.candidates import _candidates
from hostlink.images.centroid.options import (
    SATURATED_SIGMA_PX,
    CentroidOptions,
    Detections,
    FrameReport,
    _check_options,
)
from hostlink.images.centroid.psf import _noise_stated, _psf_fit_centroids, _psf_fluxes, centroid_sigma_px
from hostlink.images.centroid.screen import _extract, _less_background_frame, _screen
from hostlink.images.centroid.shapes import (
    _BLEND_MAX_BIAS_PX,
    _border_ellipticity,
    _shape_bias_px,
    _unresolved_pairs,
    _windowed_ellipticity,
)
from hostlink.images.centroid.windows import (
    _border_windows,
    _frame_psf_sigma_px,
    _psf_model_sigma_px,
    _windowed_centroids,
)


def centroid_pixels(
    pixels: np.ndarray,
    options: CentroidOptions = CentroidOptions(),  # noqa: B008 (a frozen dataclass)
    background: np.ndarray | None = None,
    saturation_adu: float | None = None,
) -> Detections:
    """Detect and centroid the stars of one image ``pixels[row, column]`` [ADU] (package docstring, steps 1-6), stage
    by stage: :func:`_extract` (background, noise, detection), :func:`_screen` (rejections before centroiding),
    :func:`_centroid_screened` (centroids, unresolved pairs, the PSF fit), :func:`_measured` (fluxes, ``sigma_px``,
    order). ``background``: a dark or median frame to subtract first; ``saturation_adu``: the clip level of ``pixels``
    (``options.saturation_adu`` wins; None: no saturation test). On one BLAS thread
    (:func:`hostlink.calibration.data.one_blas_thread`): its matrix products are small (4 x 4 normal matrices per
    star, a frame's background interpolated from a few hundred boxes), and OpenBLAS's threads would spend more time
    waiting than computing."""
    from hostlink.calibration.data import one_blas_thread

    with one_blas_thread():
        return _centroid_pixels(pixels, options, background, saturation_adu)


def _centroid_pixels(pixels, options: CentroidOptions, background, saturation_adu: float | None) -> Detections:
    """:func:`centroid_pixels`, stage by stage."""
    _check_options(options)
    raw = np.ascontiguousarray(pixels, dtype=np.float64)
    level = options.saturation_adu if options.saturation_adu is not None else saturation_adu
    blank = saturated_regions(raw, level)
    sub, rms, filtered, objects, segmap = _extract(_less_background_frame(raw, background), options, blank, raw, level)
    # numpy's partition of one array (no axis) is faster than sorting it (row_medians), its copy of the unmasked pixels
    # too: 4.5 against 9.5 ms for 1.2 Mpx
    median_rms_adu = float(np.median(rms[~blank] if blank.any() else rms))
    report = FrameReport(path="", detected=int(objects.size), background_rms_adu=median_rms_adu)
    if objects.size == 0:
        return _no_stars(report)
    screen = _screen(sub, rms, raw, objects, segmap, options, level)
    report.rejected_saturated = 0 if options.keep_saturated else int(np.count_nonzero(screen.saturated & ~screen.hot))
    report.rejected_hot = int(screen.hot.sum())
    report.rejected_blended = int(screen.blended.sum())
    if not np.any(screen.keep):
        return _no_stars(report)
    k = screen.keep
    screened = _Stars(
        objects[k]["x"].astype(np.float64),
        objects[k]["y"].astype(np.float64),
        objects[k],
        screen.saturated[k],
        screen.truncated[k],
        screen.blend_px[k],
        np.ones(int(k.sum())),
        np.full(int(k.sum()), np.nan),
    )
    stars, sigma = _centroid_screened(sub, rms, screened, options, report)
    if stars.x.size == 0:
        return _no_stars(report)
    detections = _measured(sub, rms, stars, sigma, options, report)
    fainter = options.candidate_sigma is not None and options.candidate_sigma < options.threshold_sigma
    if fainter and detections.x_px.size:  # candidates are what lies below the detection threshold
        detections.candidates = _candidates(sub, rms, filtered, screen.segmap, detections, report.psf_sigma_px, options)
        report.candidates = int(detections.candidates.x_px.size)
    return detections


def _no_stars(report: FrameReport) -> Detections:
    """The :class:`Detections` of a frame that keeps no star."""
    none = np.zeros(0, bool)
    empty = np.zeros(0)
    return Detections(empty, empty, empty, empty, report, empty, none, blended=none, blend_px=empty)


@dataclass(frozen=True)
class _Stars:
    """The stars of one frame between the stages, (N,) each: centroid [px], SEP's object, ``clipped`` (saturated),
    ``truncated`` (cut by the border), ``blend_px`` (the bound on a kept blend's centroid bias [px], NaN for a star
    not flagged as one), ``window_fraction`` (the share of its window's weight a border-cut star's windowed centroid
    used, 1 elsewhere), ``pair_px`` (the part of ``blend_px`` from the star's elongation, an unresolved companion's
    pull: the part identification's blend reference models, NaN for a star not elongated)."""

    x: np.ndarray
    y: np.ndarray
    good: np.ndarray
    clipped: np.ndarray
    truncated: np.ndarray
    blend_px: np.ndarray
    window_fraction: np.ndarray
    pair_px: np.ndarray

    def select(self, rows: np.ndarray) -> _Stars:
        """The stars ``rows`` (a boolean mask or indices)."""
        return _Stars(*(getattr(self, f)[rows] for f in self.__dataclass_fields__))


def _centroid_screened(sub, rms, stars: _Stars, options: CentroidOptions, report: FrameReport):
    """Package docstring, step 4, on the screened ``stars``: the frame's PSF sigma, windowed centroids (a star cut by
    the border: :func:`_border_windows`), the blend test (:func:`_unresolved_pairs`: a star more elongated than the
    PSF of its part of the field is kept, flagged, while the bound on its bias is at most :data:`_BLEND_MAX_BIAS_PX`,
    else rejected as blended), then the PSF model's width (:func:`_psf_model_sigma_px`: the moments keep r50's wider
    window) and the PSF fit. Returns the stars kept and the PSF model's sigma [px]."""
    clipped = stars.clipped
    sigma = options.psf_sigma_px or _frame_psf_sigma_px(sub, stars.good[~clipped] if np.any(~clipped) else stars.good)
    stars = _windowed(sub, stars, sigma, report)
    # unresolved pairs (too close for a saddle between them: the deblender sees one peak) are elongated beyond the PSF
    # of their part of the field; a clipped core's shape is not the PSF's (round where the PSF is trailed): saturated
    # stars are neither tested nor part of the PSF's shape
    e, e_sigma, size = _windowed_ellipticity(sub, rms, stars.x, stars.y, sigma, options.gain_e_per_adu)
    cut = np.flatnonzero(stars.truncated & ~stars.clipped)  # a border cuts a star's moments: the part it has
    if cut.size:
        e[cut], e_sigma[cut], size[cut] = _border_ellipticity(
            sub, rms, stars.x[cut], stars.y[cut], sigma, options.gain_e_per_adu
        )
    e_sigma[stars.clipped] = np.inf
    # a deblended star's neighbour shapes it, a border-cut one is a part: neither is the PSF's shape
    usable = ~np.isfinite(stars.blend_px) & ~stars.truncated
    elongated, excess = _unresolved_pairs(e, e_sigma, options.max_ellipticity, stars.x, stars.y, sub.shape, usable)
    bias = _shape_bias_px(excess, size)
    unresolved = elongated & ~(bias <= _BLEND_MAX_BIAS_PX)
    report.rejected_blended += int(unresolved.sum())
    flagged = elongated & ~unresolved
    blend_px = stars.blend_px.copy()
    blend_px[flagged] = np.hypot(np.nan_to_num(blend_px[flagged]), bias[flagged])
    pair_px = stars.pair_px.copy()
    pair_px[flagged] = bias[flagged]
    stars = replace(stars, blend_px=blend_px, pair_px=pair_px).select(~unresolved)
    single = ~elongated[~unresolved] & ~stars.clipped
    if options.psf_sigma_px is None and np.any(elongated) and np.any(single):  # the elongated ones widened the
        again = _frame_psf_sigma_px(sub, stars.good[single])  # first estimate
        if again != sigma:  # each star's window is its own: with the same sigma, the same centroids
            sigma = again
            stars = _windowed(sub, replace(stars, x=stars.good["x"], y=stars.good["y"]), sigma, report)
    if options.psf_sigma_px is None:  # the PSF model's own width (pixel-integrated) for the fit, flux and sigma_px,
        shaped = ~np.isfinite(stars.blend_px) & ~stars.clipped  # measured on stars of the PSF's shape (no blend)
        sigma = _psf_model_sigma_px(sub, stars.good[shaped] if np.any(shaped) else stars.good, sigma)
    report.psf_sigma_px = float(sigma)
    if options.method == "psf-fit" and stars.x.size:  # a clipped core does not follow the PSF: saturated stars keep
        fit = np.flatnonzero(~stars.clipped)  # the window
        x, y = stars.x.copy(), stars.y.copy()
        x[fit], y[fit], fitted = _psf_fit_centroids(sub, rms, x[fit], y[fit], sigma, options.gain_e_per_adu)
        fraction = stars.window_fraction.copy()
        fraction[fit[fitted]] = 1.0  # a fitted star's sigma_px is the bound over the pixels it has
        stars = replace(stars, x=x, y=y, window_fraction=fraction)
    return stars, float(sigma)


def _windowed(sub, stars: _Stars, sigma: float, report: FrameReport) -> _Stars:
    """``stars`` with SEP's windowed centroids (from their isophotal ones), those cut by the border with
    :func:`_border_windows`; a border-cut star whose window fails is rejected at the edge (counted)."""
    x, y = _windowed_centroids(sub, stars.good, sigma)
    fraction = np.ones(x.size)
    cut = np.flatnonzero(stars.truncated)
    lost = np.zeros(x.size, dtype=bool)
    if cut.size:
        xs, ys, fraction[cut] = _border_windows(sub, stars.good["x"][cut], stars.good["y"][cut], sigma)
        x[cut], y[cut] = xs, ys
        lost[cut] = ~(fraction[cut] > 0)
    report.rejected_edge += int(lost.sum())
    return replace(stars, x=x, y=y, window_fraction=fraction).select(~lost)


def _measured(sub, rms, stars: _Stars, sigma: float, options: CentroidOptions, report: FrameReport) -> Detections:
    """Package docstring, steps 5-6: each star's PSF flux (a detection without flux rejected), ``sigma_px`` and
    instrumental magnitude, brightest first (the brightest ``max_stars``). A kept blend's ``sigma_px`` adds its bias
    bound b in quadrature, per axis b / sqrt(2) (a shift of b in an unknown direction); a border-cut star centroided
    by its window (saturated, or its fit not taken) divides it by the square root of the share of the window's
    weight it used (the information of the pixels it has). ``blend_px`` of the result: the part of b from the star's
    elongation (``pair_px``), which identification takes out again where its blend reference models that pull."""
    x, y, good, clipped = stars.x, stars.y, stars.good, stars.clipped
    flux = _psf_fluxes(sub, x, y, sigma)
    # the PSF amplitude of a clipped star is too low; its isophotal sum is a lower bound that keeps it first
    flux[clipped] = np.maximum(flux[clipped], good["flux"][clipped])
    # no flux where the PSF sits: noise that crossed the threshold (no star, and no centroid noise to state)
    measured = flux > 0
    report.rejected_no_flux = int(np.count_nonzero(~measured))
    stars, flux = stars.select(measured), flux[measured]
    x, y, clipped = stars.x, stars.y, stars.clipped
    sigma_px = centroid_sigma_px(x, y, flux, rms, sigma, options.gain_e_per_adu)
    sigma_px[clipped] = np.maximum(sigma_px[clipped], SATURATED_SIGMA_PX)
    sigma_px /= np.sqrt(stars.window_fraction)
    blend = np.isfinite(stars.blend_px)
    sigma_px[blend] = np.hypot(sigma_px[blend], stars.blend_px[blend] / math.sqrt(2.0))
    # no noise measured where the star sits (every pixel around it clipped): no sigma_px, so no row
    stated = _noise_stated(sigma_px)
    report.rejected_no_flux += int(np.count_nonzero(~stated))
    stars, flux, sigma_px, blend = stars.select(stated), flux[stated], sigma_px[stated], blend[stated]
    order = np.argsort(-flux, kind="stable")
    if options.max_stars is not None:
        order = order[: options.max_stars]
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(flux > 0, -2.5 * np.log10(np.where(flux > 0, flux, 1.0)), np.nan)
    report.kept = int(order.size)
    report.saturated_kept = int(stars.clipped.sum())
    report.blended_kept = int(blend.sum())
    return Detections(
        stars.x[order],
        stars.y[order],
        flux[order],
        mag[order],
        report,
        sigma_px[order],
        stars.clipped[order],
        blended=blend[order],
        blend_px=stars.pair_px[order],
    )
