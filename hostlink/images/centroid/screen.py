"""Extraction and the screening before any centroid: SEP's background, detection and deblending, then the saturated
stars, the hot pixels, the deblended neighbours and the stars cut by the border (:mod:`hostlink.images.centroid`,
steps 1-3)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.errors import UserError, one_line
from hostlink.images.background import filtered_noise_correction, kernel_norm
from hostlink.images.centroid.options import CentroidOptions
from hostlink.images.centroid.phases import bank_detections
from hostlink.images.centroid.shapes import (
    _BLEND_CLEAR_SIGMAS,
    _BLEND_MAX_BIAS_PX,
    _nearest_neighbour_px,
    _neighbour_bias_px,
)
from hostlink.images.centroid.windows import (
    _DEFAULT_PSF_SIGMA_PX,
    _MIN_PSF_SIGMA_PX,
    _frame_psf_sigma_px,
    _psf_model_sigma_px,
)
from hostlink.sky.render import pixel_integrated_gaussian

#: The detection filter (SEP's default 3 x 3 kernel, a Gaussian of sigma ~1 px sampled on pixels).
_FILTER_KERNEL = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]], dtype=np.float32)


#: SEP's buffer of pixels above the threshold: its default first, then this when a frame fills it (a noisy frame at a
#: low threshold can hold many more). Only the buffer's size differs, not what is extracted: SEP either fills it and
#: stops with an error or does not; the large one is costly to set up for every frame (docs/realsky.md, "Time").
_SEP_PIXSTACK_FIRST = 300_000


_SEP_PIXSTACK = 3_000_000


#: SEP's cleaning (Source Extractor's CLEAN: a detection its bright neighbour's modelled wing could explain is merged
#: into it) is off: on the granasat frames it removed sharp stars of 8-16 sigma 8-18 px from a bright one (the
#: stars the plate solver names; found with it off, at the same threshold and footprint). What cleaning guards
#: against, bumps on a bright star's wing, the blend test and the PSF fit's flux see.
_SEP_CLEAN = False


_SEP_SUB_OBJECTS = 4096


def _less_background_frame(raw: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """``raw`` less the dark or median frame ``background`` (a copy, which :func:`_extract` then changes in place; a
    frame of another size is a UserError)."""
    if background is None:
        return raw.copy()
    if background.shape != raw.shape:
        raise UserError(
            f"background frame is {background.shape[1]} x {background.shape[0]} px, image is "
            f"{raw.shape[1]} x {raw.shape[0]} px"
        )
    return raw - background


def _extract(
    data: np.ndarray,
    options: CentroidOptions,
    blank: np.ndarray | None = None,
    raw: np.ndarray | None = None,
    level: float | None = None,
):
    """Package docstring, steps 1-2: SEP's background mesh subtracted (``blank``, the blank regions of
    :func:`hostlink.images.background.saturated_regions`, masked from it and from the detection), its noise map
    corrected to what the detection filter sees, box by box (:func:`hostlink.images.background.
    filtered_noise_correction`), then SEP's matched-filter detection and deblending, with the minimum footprint
    matched to the frame's PSF: measured on the stars of a first extraction (those with a pixel of ``raw`` at the
    clip level ``level`` left out), and where it is undersampled (:func:`_footprint_px`) the extraction again with a
    footprint of 1 filtered pixel, a detection of 1 pixel kept at :data:`_SINGLE_PIXEL_THRESHOLD` x the threshold
    (:func:`_single_pixels_kept`). Returns the background-subtracted image, the noise map [ADU], the detection's
    significance (the filtered image over its noise, what the threshold is compared with), SEP's objects and its
    segmentation map. A float64 C-contiguous ``data`` is the frame's own: the background is subtracted from it in
    place (:func:`_less_background_frame` makes it)."""
    import sep

    box = int(min(options.background_box_px, max(8, min(data.shape) // 2)))
    sep.set_sub_object_limit(_SEP_SUB_OBJECTS)
    try:
        blank = np.zeros(data.shape, dtype=bool) if blank is None else blank
        sub = np.ascontiguousarray(data, dtype=np.float64)
        bkg = sep.Background(sub, mask=blank, bw=box, bh=box, fw=3, fh=3)
        bkg.subfrom(sub)  # in place: the numbers of sub - bkg.back(), in half the time
        offset, rms, filtered, ignored = filtered_noise_correction(
            sub, bkg.rms, _FILTER_KERNEL, box, blank, bkg.globalback
        )
        sub -= offset
        del offset  # a frame-sized float64 array no longer needed (the frame's peak memory: docs/realsky.md)
        objects, segmap = _sep_extract(sep, sub, rms, ignored, options, options.min_area_px)
    except Exception as exc:  # SEP reports buffer overflows as plain exceptions
        raise _extraction_failed(exc) from None
    # filtered / (rms x norm) in filtered's own array, a strip of rows at a time: the divisor's strip is the only
    # temporary (a frame-sized one was the stage's peak on a large frame: docs/realsky.md, "Large frames")
    significance, rows = filtered, max(1, _SIGNIFICANCE_STRIP_ELEMENTS // max(filtered.shape[1], 1))
    for start in range(0, significance.shape[0], rows):
        significance[start : start + rows] /= rms[start : start + rows] * _FILTERED_NOISE_PER_PX
    # the PSF measured outside the guard: a failure of ours there is not SEP's, nor cured by a higher threshold
    sigma = options.psf_sigma_px or _first_pass_psf_sigma_px(sub, objects, segmap, raw, level)
    min_area = _footprint_px(sigma, options.min_area_px) if options.footprint_follows_psf else options.min_area_px
    if min_area < options.min_area_px:
        try:
            objects, segmap = _sep_extract(sep, sub, rms, ignored, options, min_area)
        except Exception as exc:
            raise _extraction_failed(exc) from None
        objects, segmap = _single_pixels_kept(objects, segmap, significance, options)
    if options.footprint_follows_psf:  # the bank of half-pixel phases, on the frames of a sharp PSF
        objects, segmap = bank_detections(
            sub, rms, ignored, objects, segmap, significance, sigma, options.threshold_sigma
        )
    return sub, rms, significance, objects, segmap


def _extraction_failed(exc: Exception) -> UserError:
    """The one-line error of a failed background or extraction (SEP's own message, and the cure)."""
    return UserError(f"source extraction failed ({one_line(exc)}); raise --threshold-sigma")


#: The filtered image's noise per unit of the per-pixel noise (the detection kernel normalised: sqrt(sum k^2)).
_FILTERED_NOISE_PER_PX = kernel_norm(_FILTER_KERNEL)
#: The significance is divided this many pixels at a time (:func:`_extract`: a float64 strip of 2 MB).
_SIGNIFICANCE_STRIP_ELEMENTS = 1 << 18


def _first_pass_psf_sigma_px(sub, objects: np.ndarray, segmap, raw, level: float | None) -> float:
    """The PSF model's sigma [px] (:func:`_psf_model_sigma_px`, started from the half-light radius's,
    :func:`_frame_psf_sigma_px`) measured on the first extraction's stars that are neither single-pixel spikes
    (:func:`_single_pixel_spikes`), saturated (a pixel of ``raw`` at ``level``: a clipped core is wider than the
    PSF), cut by the border nor deblended."""
    import sep

    if objects.size == 0:
        return _DEFAULT_PSF_SIGMA_PX
    flagged = (objects["flag"] & (sep.OBJ_TRUNC | sep.OBJ_MERGED)) != 0
    usable = ~_single_pixel_spikes(sub, objects) & ~flagged
    if raw is not None and level is not None:
        usable &= ~_saturated_objects(raw, segmap, level, objects.size)
    good = objects[usable] if np.any(usable) else objects
    return _psf_model_sigma_px(sub, good, _frame_psf_sigma_px(sub, good))


def _saturated_objects(raw: np.ndarray, segmap: np.ndarray, level: float, n_objects: int) -> np.ndarray:
    """(N,) bool: SEP's objects with a raw pixel of their footprint at the clip level ``level``."""
    _, labels = _clipped_footprint_pixels(raw, segmap, level)
    return np.bincount(labels, minlength=n_objects + 1)[1:] > 0


def _clipped_footprint_pixels(raw: np.ndarray, segmap: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """The flat indices of the pixels of ``raw`` at the clip level ``level`` inside a footprint of SEP's
    segmentation map, and their objects' labels (from 1): one pass over the frame, the footprints looked up at the few
    clipped pixels only."""
    at_level = np.flatnonzero(raw >= level)
    labels = segmap.ravel()[at_level]
    inside = labels > 0
    return at_level[inside], labels[inside]


#: Where the footprint is 1 filtered pixel (:func:`_footprint_px`), a detection of 1 pixel above the threshold is
#: kept when its filtered peak reaches this factor x the threshold (those of 2 pixels or more are kept as before):
#: white noise filtered by SEP's kernel then gives a tenth more detections than SEP's footprint of 2 alone (the
#: local maxima with and without a second pixel above the threshold: docs/realsky.md, "Binned and undersampled
#: frames", tests/test_centroid_undersampled_detection.py); holding the footprint of 2's false-alarm rate exactly
#: would have dropped 2-pixel detections too, which lost named stars.
_SINGLE_PIXEL_THRESHOLD = 1.2


#: The footprint follows the PSF (:func:`_footprint_px`) only where that lowers the mean flux a star needs to be
#: detected by more than this factor (:func:`_footprint_gain`): a smaller gain is not worth the second extraction,
#: and the frames of a PSF sigma over ~0.575 px keep SEP's footprint alone.
_FOOTPRINT_MIN_GAIN = 1.05


#: Sub-pixel phases of a star over which its filtered image is averaged [px] (the midpoints of fifths of a pixel).
_PHASES_PX = (np.arange(5) + 0.5) / 5 - 0.5


def _filtered_stars(sigma_px: float) -> np.ndarray:
    """(phases, pixels) the significance image of a star of unit flux and PSF sigma ``sigma_px`` (the
    pixel-integrated Gaussian) on unit white noise filtered by SEP's kernel (sum k I / sqrt(sum k^2), the matched
    filter's statistic), one row per sub-pixel phase of :data:`_PHASES_PX`."""
    from scipy import ndimage

    half = _FILTER_KERNEL.shape[0] // 2 + math.ceil(3.0 * sigma_px) + 1
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    k = _FILTER_KERNEL.astype(np.float64) / float(_FILTER_KERNEL.sum())  # unit sum, as kernel_norm's
    rows = []
    for dy in _PHASES_PX:
        py = pixel_integrated_gaussian(offsets, dy, sigma_px)
        for dx in _PHASES_PX:
            star = np.outer(py, pixel_integrated_gaussian(offsets, dx, sigma_px))
            rows.append(ndimage.correlate(star, k, mode="constant").ravel() / _FILTERED_NOISE_PER_PX)
    return np.array(rows)


def _footprint_gain(sigma_px: float) -> float:
    """How much less flux, on average over sub-pixel phases, a star of PSF sigma ``sigma_px`` needs to be detected
    with a single-pixel footprint beside SEP's (:func:`_filtered_stars`: its second-highest filtered pixel at the
    threshold, or its peak at :data:`_SINGLE_PIXEL_THRESHOLD` x it) than with SEP's footprint of 2 alone: 1.073 at a
    PSF sigma of 0.45 px, 1.054 at 0.55 px, 1.046 at 0.6 px, 1.026 at 0.77 px."""
    top = -np.sort(-_filtered_stars(sigma_px), axis=1)
    two_pixels = 1.0 / top[:, 1]
    return float(np.mean(two_pixels) / np.mean(np.minimum(two_pixels, _SINGLE_PIXEL_THRESHOLD / top[:, 0])))


def _footprint_px(sigma_px: float, min_area_px: int) -> int:
    """The minimum footprint of the detection: 1 filtered pixel where that gains more than
    :data:`_FOOTPRINT_MIN_GAIN` (:func:`_footprint_gain`; the thresholds are set for SEP's default footprint of 2),
    else ``min_area_px``. A detection of 1 pixel is then kept at :data:`_SINGLE_PIXEL_THRESHOLD` x the threshold
    (:func:`_single_pixels_kept`) and only when it fits a star better than a hot pixel (:func:`_screen`)."""
    if min_area_px == 2 and _footprint_gain(sigma_px) > _FOOTPRINT_MIN_GAIN:
        return 1
    return min_area_px


def _single_pixels_kept(objects: np.ndarray, segmap: np.ndarray, significance: np.ndarray, options: CentroidOptions):
    """(objects, segmentation map) less the detections under ``options.min_area_px`` whose filtered peak is under
    :data:`_SINGLE_PIXEL_THRESHOLD` x ``options.threshold_sigma`` (their footprints cleared), the others
    renumbered."""
    peak = significance[objects["ycpeak"], objects["xcpeak"]]
    keep = (objects["npix"] >= options.min_area_px) | (peak >= _SINGLE_PIXEL_THRESHOLD * options.threshold_sigma)
    label = np.zeros(objects.size + 1, dtype=segmap.dtype)
    label[1:][keep] = np.arange(1, int(np.count_nonzero(keep)) + 1)
    return objects[keep], label[segmap]


def _sep_extract(sep, sub, rms, ignored, options: CentroidOptions, min_area_px: int):
    """``sep.extract`` of :func:`_extract` with SEP's default pixel buffer, again with :data:`_SEP_PIXSTACK` when a
    frame fills it (the same extraction either way)."""

    def extract():
        return sep.extract(
            sub,
            options.threshold_sigma,
            err=rms,
            mask=ignored,
            minarea=min_area_px,
            filter_kernel=_FILTER_KERNEL,
            deblend_nthresh=32,
            deblend_cont=0.005,
            clean=_SEP_CLEAN,
            segmentation_map=True,
        )

    sep.set_extract_pixstack(_SEP_PIXSTACK_FIRST)
    try:
        return extract()
    except Exception as exc:
        if "pixel buffer full" not in str(exc):
            raise
    sep.set_extract_pixstack(_SEP_PIXSTACK)
    return extract()


@dataclass(frozen=True)
class _Screen:
    """The rejections before centroiding (package docstring, step 3), (N,) over SEP's objects: ``keep``, and each
    rejection counted once, in order (hot, saturated only when not kept, blended); ``saturated``: a raw pixel of the
    footprint at the clip level (kept or not); ``truncated``: cut by the border (centroided on the pixels it has,
    :func:`_border_windows`); ``blend_px``: the bias bound [px] of a deblended star kept beside a neighbour
    (:func:`_neighbour_bias_px`), NaN for the others; ``segmap``: SEP's segmentation map less the footprints of the
    detections under ``min_area_px`` rejected as hot (below the footprint's standard, where a faint star of an
    undersampled PSF fits a spike as well: they stay for the candidates to judge, as before the footprint followed
    the PSF)."""

    keep: np.ndarray
    saturated: np.ndarray
    hot: np.ndarray
    blended: np.ndarray
    truncated: np.ndarray
    blend_px: np.ndarray
    segmap: np.ndarray


def _screen(sub, rms, raw, objects, segmap, options: CentroidOptions, level: float | None) -> _Screen:
    """Package docstring, step 3, before any centroid: saturated, hot pixels and deblended neighbours; the stars cut by
    the border marked."""
    import sep

    truncated = (objects["flag"] & sep.OBJ_TRUNC) != 0
    # saturated: a raw pixel of the footprint at the clip level
    saturated = np.zeros(objects.size, bool)
    if level is not None:
        saturated = _saturated_objects(raw, segmap, level, objects.size)
    merged = (objects["flag"] & sep.OBJ_MERGED) != 0
    # hot pixels: the frame's PSF measured first on the detections that are neither single-pixel spikes by a coarse
    # screen nor clipped, then every detection tested against it (a sharp star passes, a spike does not)
    psf_hot = options.psf_sigma_px
    if psf_hot is None:
        screened = ~_single_pixel_spikes(sub, objects) & ~saturated & ~truncated & ~merged
        psf_hot = _frame_psf_sigma_px(sub, objects[screened] if np.any(screened) else objects)
    # a detection smaller than the minimum footprint (an undersampled frame's, :func:`_footprint_px`) is kept only
    # when a star explains it better than a spike: the footprint kept single pixels out, the likelihood ratio does
    small = objects["npix"] < options.min_area_px
    limit = np.where(small, 0.0, options.hot_pixel_chi2)
    hot = _hot_pixels(sub, rms, objects, psf_hot, limit) & ~saturated
    if level is not None:  # a hot pixel the clip level cuts (an 8-bit camera's reads 255)
        hot |= _clipped_spikes(sub, rms, raw, segmap, level, objects.size)
    # a deblended star whose neighbours all lie beyond the PSF fit's reach is measured as a single one; one nearer is
    # kept, flagged, with its centroid's bias bound from its neighbours' light, unless that bound exceeds the limit
    near = merged & (_nearest_neighbour_px(objects["x"], objects["y"], merged) <= _BLEND_CLEAR_SIGMAS * psf_hot)
    bias = _neighbour_bias_px(objects, near, psf_hot)
    blended = near & ~(bias <= _BLEND_MAX_BIAS_PX)
    blend_px = np.where(near & ~blended, bias, np.nan)
    keep = np.ones(objects.size, bool)
    rejected_saturated = saturated.copy() if not options.keep_saturated else np.zeros(objects.size, bool)
    for mask in (hot, rejected_saturated, blended):  # a clipped hot pixel is hot, not a saturated star
        mask &= keep
        keep &= ~mask
    if np.any(small & hot):
        segmap = np.where(np.concatenate([[False], small & hot])[segmap], 0, segmap)
    return _Screen(keep, saturated, hot, blended, truncated, blend_px, segmap)


#: Coarse screen for single-pixel spikes, used only to choose the stars the frame's PSF is measured on: the mean of
#: the 4 edge neighbours of the brightest pixel below this fraction of it (a pixel-integrated Gaussian of sigma s has
#: at least [Phi(1.5/s) - Phi(0.5/s)] / [2 Phi(0.5/s) - 1]: 0.23 at s = 0.5 px, 0.63 at s = 1 px).
_SPIKE_SCREEN_RATIO = 0.2


#: Hot-pixel test box: +-2 px around the brightest pixel (a PSF of sigma <= 1.5 px puts most of its flux inside).
_HOT_BOX_HALF_PX = 2


#: Hot-pixel test: a spike model fits when its chi^2 is within this many standard deviations sqrt(2 dof) of its
#: degrees of freedom (pure noise around the one pixel); a bright star whose core is sharper than the Gaussian
#: model fits neither model well, and the spike far worse: it is no hot pixel.
_HOT_FIT_SIGMAS = 5.0


#: Hot-pixel test: the star model's width ranges from this fraction of the frame's PSF sigma (at least
#: :data:`_MIN_PSF_SIGMA_PX`) to the full sigma. The frame's sigma is measured on its most significant stars, which an
#: 8-bit or JPEG camera widens (saturated cores, blooming, compression); a faint star's in-focus core can be half as
#: wide (on granasat 0.45-0.5 px against the frame's 0.91 px: stars the plate solver names, lost as "hot" before).
_HOT_SHARPEST_FRACTION = 0.5


#: Hot-pixel test: sub-pixel positions of the star model tried around the brightest pixel's centre [px].
_HOT_POSITIONS_PX = np.linspace(-0.5, 0.5, 5)


def _single_pixel_spikes(sub: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """The coarse screen of :data:`_SPIKE_SCREEN_RATIO` (not a rejection: it keeps spikes out of the PSF
    measurement that the rejection test :func:`_hot_pixels` then uses)."""
    h, w = sub.shape
    c = np.clip(objects["xpeak"].astype(np.int64), 1, w - 2)
    r = np.clip(objects["ypeak"].astype(np.int64), 1, h - 2)
    peak = sub[r, c]
    neighbours = (sub[r - 1, c] + sub[r + 1, c] + sub[r, c - 1] + sub[r, c + 1]) / 4.0
    return neighbours < _SPIKE_SCREEN_RATIO * peak


def _orthonormal_bases(columns: list[np.ndarray]) -> np.ndarray:
    """(P, M, 2) orthonormal bases U of the span of each design matrix (P, 2) of ``columns`` (QR): the orthogonal
    projector onto the m-th span is U[:, m] U[:, m]^T. One batched QR (the same LAPACK call per matrix)."""
    return np.swapaxes(np.linalg.qr(np.stack(columns))[0], 0, 1)


#: A clipped pixel is a hot one when its edge neighbours' mean lies this many of its noise below what the sharpest
#: star would put there (:func:`_clipped_spikes`).
_CLIPPED_SPIKE_SIGMAS = 5.0


def _clipped_spikes(sub, rms, raw, segmap, level: float, n_objects: int) -> np.ndarray:
    """(N,) bool: hot pixels the clip level cuts, which :func:`_hot_pixels` cannot judge (a clipped pixel is a lower
    bound, not a value): a detection with exactly one pixel at the clip level whose 4 edge neighbours (those inside
    the image) hold, on average, less than any star able to clip it would put there. A pixel-integrated Gaussian of
    sigma s centred on a pixel puts r = P(1) / P(0) of its peak pixel's signal into each edge neighbour, the least of
    any position (off centre the peak pixel falls and the neighbours' mean rises), r = 0.18 for the sharpest star,
    s = :data:`_MIN_PSF_SIGMA_PX` (not a fraction of the frame's PSF: on a trailed frame, granasat's polar_30sec, the
    frame's PSF is 1.5 px and stars with a single clipped pixel are far sharper); a clipped peak holds at least the
    clip level less the background. Hot when the neighbours' mean (less the
    background) is below r (level - background) - :data:`_CLIPPED_SPIKE_SIGMAS` x noise / 2 (the noise of a mean of
    4). A saturated star's core of several clipped pixels, or one whose wings are there, is kept."""
    out = np.zeros(n_objects, dtype=bool)
    at_level, labels = _clipped_footprint_pixels(raw, segmap, level)
    rows, cols = np.divmod(at_level, raw.shape[1])
    counts = np.bincount(labels, minlength=n_objects + 1)
    single = counts[labels] == 1
    rows, cols, labels = rows[single], cols[single], labels[single]
    if labels.size == 0:
        return out
    h, w = sub.shape
    total, number = np.zeros(labels.size), np.zeros(labels.size)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        total[inside] += sub[r[inside], c[inside]]
        number += inside
    peak, edge = pixel_integrated_gaussian(np.array([0.0, 1.0]), 0.0, _MIN_PSF_SIGMA_PX)
    height = level - (raw[rows, cols] - sub[rows, cols])  # the clip level above the local background
    least = (edge / peak) * height - _CLIPPED_SPIKE_SIGMAS * rms[rows, cols] / 2.0
    out[labels[total / np.maximum(number, 1) < least] - 1] = True
    return out


def _hot_bases(offsets: np.ndarray, dr: int, dc: int, widths: np.ndarray) -> np.ndarray:
    """The orthonormal bases (P, M, 2) of :func:`_hot_pixels`' models over the box ``offsets`` x ``offsets`` with
    the brightest pixel at (``dr``, ``dc``) from its centre: the spike on it, then the star at each width and
    sub-pixel position around it, each with a flat background."""
    flat = np.ones(offsets.size**2)
    spike = np.zeros((offsets.size, offsets.size))
    spike[dr + offsets.size // 2, dc + offsets.size // 2] = 1.0
    # every width's factors at every sub-pixel position in one call each: (widths, positions, pixels), elementwise the
    # numbers of one call per model
    at = offsets[None, None, :].astype(np.float64)
    py = pixel_integrated_gaussian(at, dr + _HOT_POSITIONS_PX[None, :, None], widths[:, None, None])
    px = pixel_integrated_gaussian(at, dc + _HOT_POSITIONS_PX[None, :, None], widths[:, None, None])
    stars = (py[:, :, None, :, None] * px[:, None, :, None, :]).reshape(-1, offsets.size**2)  # (width, dy, dx) order
    return _orthonormal_bases([np.column_stack([m, flat]) for m in [spike.ravel(), *stars]])


def _hot_pixels(
    sub: np.ndarray, rms: np.ndarray, objects: np.ndarray, psf_sigma_px: float, chi2_limit: float | np.ndarray
):
    """Hot pixels: detections that a single bright pixel explains better than a star of the frame's own PSF, by a
    likelihood-ratio test. Over the (2h+1)^2 pixels d around the brightest one (h = :data:`_HOT_BOX_HALF_PX`), in
    units of the local noise, two linear models each with a flat background: a spike (amplitude on the central pixel
    only) and the pixel-integrated Gaussian of sigma ``psf_sigma_px`` (:func:`hostlink.sky.render.
    pixel_integrated_gaussian`) at the best of a 5 x 5 grid of sub-pixel positions and of three widths from
    :data:`_HOT_SHARPEST_FRACTION` of it to all of it; chi^2 = |d|^2 - d^T Q d for each
    model's projector Q. A detection is a hot pixel when chi^2_star - chi^2_spike > ``chi2_limit`` (one for all, or
    (N,) one per detection: :func:`_screen` holds those under the minimum footprint to 0): the star model is
    rejected (both have 2 free amplitudes: under a true star the difference is noise of a few units, under a spike
    of amplitude A it grows as (A / noise)^2). A sharp star (sigma 0.5-0.8 px), whose neighbours hold little of
    its flux, still fits its PSF better than a spike; a faint star, whose neighbours are lost in the noise, fits
    both about as well and is kept; and only a spike that fits the pixels (its chi^2 within :data:`_HOT_FIT_SIGMAS`
    standard deviations of its degrees of freedom: nothing but noise around one pixel) is one, so a bright star
    whose real core is sharper than the Gaussian (the spike then fits far worse still) is kept. Returns (N,) bool."""
    h, w = sub.shape
    half = _HOT_BOX_HALF_PX
    if objects.size == 0:
        return np.zeros(0, dtype=bool)
    peak_c, peak_r = objects["xpeak"].astype(np.int64), objects["ypeak"].astype(np.int64)
    c = np.clip(peak_c, half, w - 1 - half)
    r = np.clip(peak_r, half, h - 1 - half)
    offsets = np.arange(-half, half + 1)
    cut = sub[r[:, None, None] + offsets[None, :, None], c[:, None, None] + offsets[None, None, :]]
    d = cut.reshape(objects.size, -1) / np.maximum(rms[r, c], 1e-12)[:, None]
    widths = np.geomspace(max(_MIN_PSF_SIGMA_PX, _HOT_SHARPEST_FRACTION * psf_sigma_px), psf_sigma_px, 3)
    # the box lies inside the image: near the border the brightest pixel is off its centre, and both models with it
    shift = (peak_r - r) * offsets.size + (peak_c - c)
    explained = np.zeros((objects.size, 1 + widths.size * _HOT_POSITIONS_PX.size**2))
    for value in np.unique(shift):
        rows = np.flatnonzero(shift == value)
        dr, dc = divmod(int(value) + half * (offsets.size + 1), offsets.size)
        basis = _hot_bases(offsets, dr - half, dc - half, widths)
        # d^T Q d = |U^T d|^2 for the projector Q = U U^T of each model (U: an orthonormal basis of its 2 columns)
        explained[rows] = np.sum((d[rows] @ basis.reshape(d.shape[1], -1)).reshape(rows.size, -1, 2) ** 2, axis=2)
    total = np.einsum("np,np->n", d, d)
    chi2_spike = total - explained[:, 0]
    chi2_star = total - np.max(explained[:, 1:], axis=1)
    dof = d.shape[1] - 2
    spike_fits = chi2_spike <= dof + _HOT_FIT_SIGMAS * math.sqrt(2.0 * dof)
    return spike_fits & (chi2_star - chi2_spike > chi2_limit)
