"""A second detection pass for undersampled frames: a bank of matched filters of the PSF's own width at half-pixel
phases (:mod:`hostlink.images.centroid`, step 1, after SEP's extraction).

SEP's 3 x 3 kernel reaches 0.86 of the ideal matched filter's significance for a star of PSF sigma 0.45 px, averaged
over sub-pixel phases: a star at a pixel's corner spreads its light over 4 pixels that a kernel centred on one pixel
weighs badly. The bank holds the pixel-integrated Gaussian of the frame's PSF width centred on a pixel, on the right
edge, the lower edge and the corner (4 kernels, separable); the maximum of the 4 significance images reaches
0.97 of the ideal there (docs/realsky.md, "Binned and undersampled frames"). The maximum of 4 correlated images
holds more noise maxima than one image, so its threshold is raised (:data:`_BANK_THRESHOLDS`) to hold the false-alarm
rate; the bank then decides the faint detections: its local maxima that SEP's extraction missed are added, as
detections of 1 pixel measured afterwards on the frame's own pixels (the windowed centroid, the PSF fit, the hot-pixel
test with a star needing to fit better than a spike) as the detections of the footprint of 1 are
(:func:`hostlink.images.centroid.screen._footprint_px`), and SEP's faint detections stay only where the bank confirms
them (:data:`_SEP_CONFIRMED_ABOVE`). Searched on frames of a PSF sigma under 0.85 px detected at 3.5 sigma or more."""

from __future__ import annotations

import math

import numpy as np

from hostlink.sky.render import pixel_integrated_gaussian

#: The kernels' centres relative to the pixel they are applied at [px], per axis: the pixel's centre and its edge.
_BANK_PHASES_PX = (0.0, 0.5)


#: The bank's threshold, as a factor of the detection threshold, by the frame's PSF sigma: (the PSF sigma [px] it holds
#: under, factor). A local maximum of the bank at that factor x the threshold is a detection. Each factor is the least
#: of 1.15, 1.17, 1.2 at which the whole centroid stage, on white Gaussian noise and on 8-bit noise clipped at 0
#: (a dark frame of 3 ADU, 2 ADU of noise), keeps no more detections than without the bank (docs/realsky.md,
#: "Binned and undersampled frames": the maximum of 4 correlated significance images holds more noise maxima than
#: one, the more so the sharper the kernels); tests/test_centroid_phase_bank.py measures the rate. Frames of a wider
#: PSF are not searched (the gain over SEP's kernel falls under 2.5 %, :func:`bank_gain`).
_BANK_THRESHOLDS = ((0.75, 1.2), (0.85, 1.17))


#: Where the bank is searched, a detection of SEP's whose filtered peak (SEP's kernel) is under this factor x the
#: threshold is kept only when the bank confirms it (its maximum over the footprint at the bank's threshold): the bank,
#: not SEP's kernel, decides the faint detections, so that its maxima replace SEP's kernel's noise detections instead
#: of adding to them (docs/realsky.md, "Binned and undersampled frames").
_SEP_CONFIRMED_ABOVE = 1.5


#: The bank is searched only at a detection threshold of at least this many sigmas: the factors of
#: :data:`_BANK_THRESHOLDS` hold the false-alarm rate at 3.5 and 4 sigma, and the bank's share of the noise maxima
#: grows as the threshold falls (at 3 sigma, 0.45 px: 2186 detections on 6 Mpx of white noise against 1968).
_BANK_MIN_THRESHOLD_SIGMA = 3.5


def bank_threshold(sigma_px: float, threshold_sigma: float = _BANK_MIN_THRESHOLD_SIGMA) -> float | None:
    """The bank's threshold factor for a frame of PSF sigma ``sigma_px`` detected at ``threshold_sigma``
    (:data:`_BANK_THRESHOLDS`); None: the frame is not searched with the bank (its PSF too wide, or the threshold
    under :data:`_BANK_MIN_THRESHOLD_SIGMA`)."""
    if not threshold_sigma >= _BANK_MIN_THRESHOLD_SIGMA:
        return None
    for below, factor in _BANK_THRESHOLDS:
        if sigma_px < below:
            return factor
    return None


def _bank_half_px(sigma_px: float) -> int:
    """The kernels' half size [px]: 3 sigma beyond the half-pixel phase, at least 1."""
    return max(1, math.ceil(3.0 * sigma_px + 0.5))


def _bank_profiles(sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(profiles (2, n), norms (2,)): the 1-D pixel-integrated Gaussian of ``sigma_px`` centred at each of
    :data:`_BANK_PHASES_PX` over the offsets -h..h, each normalised to unit sum, and its sqrt(sum p^2). The 2-D
    kernel of phases (a, b) is the outer product, its norm the product of the norms (separable)."""
    half = _bank_half_px(sigma_px)
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    profiles = np.array([pixel_integrated_gaussian(offsets, p, sigma_px) for p in _BANK_PHASES_PX])
    profiles /= profiles.sum(axis=1, keepdims=True)
    return profiles, np.sqrt(np.sum(profiles**2, axis=1))


def bank_significance(sub: np.ndarray, rms: np.ndarray, sigma_px: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """(significance, the 4 filtered images): the maximum over the 4 kernels of :func:`_bank_profiles` of the image
    ``sub`` [ADU] correlated with the kernel k (the matched filter of a star centred at the kernel's phase from the
    pixel), over its noise ``rms`` sqrt(sum k^2) (``rms``: the per-pixel noise map whose filtered noise that is, as
    :func:`hostlink.images.background.filtered_noise_correction`'s); the filtered images (over sqrt(sum k^2), not
    ``rms``) in the order 2 a + b for the phases a along rows, b along columns (:func:`_bank_phase`)."""
    from scipy import ndimage

    profiles, norms = _bank_profiles(sigma_px)
    image = np.asarray(sub, dtype=np.float64)
    across = [ndimage.correlate1d(image, p, axis=1, mode="nearest") for p in profiles]
    images = []
    for pa, na in zip(profiles, norms, strict=True):
        for nb, row_filtered in zip(norms, across, strict=True):
            value = ndimage.correlate1d(row_filtered, pa, axis=0, mode="nearest")
            value /= na * nb
            images.append(value)
    best = images[0].copy()
    for value in images[1:]:
        np.maximum(best, value, out=best)
    best /= rms
    return best, images


def _bank_phase(images: list[np.ndarray], rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(K,) which of the 4 filtered images of :func:`bank_significance` is highest at each pixel (``rows``,
    ``cols``): 2 a + b for the phases a along rows, b along columns (the first of equal ones)."""
    return np.argmax(np.stack([value[rows, cols] for value in images]), axis=0)


def _local_maxima(image: np.ndarray, limit: float, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels of ``image`` at least ``limit`` where ``allowed``, one pixel or more from the
    border, and not below any of their 8 neighbours."""
    h, w = image.shape
    inner = image[1 : h - 1, 1 : w - 1]
    rows, cols = np.nonzero((inner >= limit) & allowed[1 : h - 1, 1 : w - 1])
    rows, cols = rows + 1, cols + 1
    value = image[rows, cols]
    peak = np.ones(rows.size, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= value >= image[rows + dr, cols + dc]
    return rows[peak], cols[peak]


def bank_new_maxima(
    significance: np.ndarray, segmap: np.ndarray, ignored: np.ndarray, limit: float
) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the bank's local maxima (``significance``, :func:`bank_significance`) at least ``limit`` that
    SEP's extraction missed: neither on nor beside (8 neighbours) a footprint of ``segmap``, nor on or beside an
    ``ignored`` pixel."""
    rows, cols = _local_maxima(significance, limit, np.ones(significance.shape, dtype=bool))
    taken = (segmap > 0) | ignored
    clear = np.ones(rows.size, dtype=bool)
    for dr in (-1, 0, 1):  # a local maximum lies a pixel or more inside the border
        for dc in (-1, 0, 1):
            clear &= ~taken[rows + dr, cols + dc]
    return rows[clear], cols[clear]


def bank_confirmed(
    objects: np.ndarray,
    segmap: np.ndarray,
    sep_significance: np.ndarray,
    bank: np.ndarray,
    threshold_sigma: float,
    factor: float,
) -> np.ndarray:
    """(N,) bool: SEP's ``objects`` that the bank keeps: a filtered peak (``sep_significance``, SEP's kernel) of at
    least :data:`_SEP_CONFIRMED_ABOVE` x ``threshold_sigma``, or the bank's significance ``bank`` reaching ``factor``
    x it somewhere on the footprint (``segmap``)."""
    peak = sep_significance[objects["ycpeak"], objects["xcpeak"]]
    labelled = segmap > 0
    best = np.full(objects.size + 1, -np.inf)
    np.maximum.at(best, segmap[labelled], bank[labelled])
    return (peak >= _SEP_CONFIRMED_ABOVE * threshold_sigma) | (best[1:] >= factor * threshold_sigma)


def bank_detections(
    sub: np.ndarray,
    rms: np.ndarray,
    ignored: np.ndarray,
    objects: np.ndarray,
    segmap: np.ndarray,
    sep_significance: np.ndarray,
    sigma_px: float,
    threshold_sigma: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(objects, segmentation map) of a frame of PSF sigma ``sigma_px`` searched with the bank (at
    :func:`bank_threshold`'s factor; a frame it does not search is returned as it is): SEP's ``objects`` and
    ``segmap`` less those the bank does not confirm
    (:func:`bank_confirmed`; their footprints cleared, the others renumbered), with the bank's new maxima
    (:func:`bank_new_maxima`) appended as detections of 1 pixel in SEP's record layout: the position the maximum's
    kernel centres (the pixel plus its phase), the peak pixel, ``flux`` the 3 x 3 sum of ``sub`` around it (the
    neighbours' bias bound weighs by it), ``cpeak`` 0 (what ranks the stars the PSF is measured on,
    :func:`hostlink.images.centroid.windows._psf_stars`, over ``thresh``: a faint star found at half-pixel phases is
    the last to measure the PSF by; ranked by their significance, they took the measured width of a rendered 0.77 px
    field down to 0.56 px), no flag, and a footprint of that one pixel."""
    factor = bank_threshold(sigma_px, threshold_sigma)
    if factor is None:
        return objects, segmap
    significance, images = bank_significance(sub, rms, sigma_px)
    significance[ignored] = 0.0
    keep = bank_confirmed(objects, segmap, sep_significance, significance, threshold_sigma, factor)
    label = np.zeros(objects.size + 1, dtype=segmap.dtype)
    label[1:][keep] = np.arange(1, int(np.count_nonzero(keep)) + 1)
    objects, segmap = objects[keep], label[segmap]
    rows, cols = bank_new_maxima(significance, segmap, ignored, factor * threshold_sigma)
    if rows.size == 0:
        return objects, segmap
    added = np.zeros(rows.size, dtype=objects.dtype)
    phase = np.asarray(_BANK_PHASES_PX)
    a, b = np.divmod(_bank_phase(images, rows, cols), len(_BANK_PHASES_PX))
    added["x"], added["y"] = cols + phase[b], rows + phase[a]
    for field, value in (("xpeak", cols), ("ypeak", rows), ("xcpeak", cols), ("ycpeak", rows)):
        added[field] = value
    added["npix"] = 1
    added["flux"] = sum(sub[rows + dr, cols + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1))
    added["peak"] = sub[rows, cols]
    added["cpeak"] = 0.0
    added["thresh"] = threshold_sigma
    out = segmap.copy()
    out[rows, cols] = objects.size + 1 + np.arange(rows.size)
    return np.concatenate([objects, added]), out


def bank_gain(sigma_px: float, factor: float) -> float:
    """How much less flux, on average over sub-pixel phases, a star of PSF sigma ``sigma_px`` needs to be detected
    with the bank (its maximum at ``factor`` x the threshold, or SEP's kernel with 2 filtered pixels
    above :data:`_SEP_CONFIRMED_ABOVE` x it) than by SEP's detection as it stands for that PSF
    (:func:`hostlink.images.centroid.screen._footprint_gain`'s rule: the second-highest filtered pixel at the
    threshold, or where the footprint is 1, the peak at its raised threshold)."""
    from hostlink.images.centroid import screen

    top = -np.sort(-screen._filtered_stars(sigma_px), axis=1)
    now = 1.0 / top[:, 1]
    if screen._footprint_px(sigma_px, 2) == 1:
        now = np.minimum(now, screen._SINGLE_PIXEL_THRESHOLD / top[:, 0])
    bank = _bank_star_peaks(sigma_px)
    with_bank = np.minimum(_SEP_CONFIRMED_ABOVE / top[:, 1], factor / bank)
    return float(np.mean(now) / np.mean(with_bank))


def _bank_star_peaks(sigma_px: float) -> np.ndarray:
    """(phases,) the bank's highest significance (:func:`bank_significance`) for a star of unit flux and PSF sigma
    ``sigma_px`` on unit white noise, at each sub-pixel phase of
    :data:`hostlink.images.centroid.screen._PHASES_PX` (both axes)."""
    from scipy import ndimage

    from hostlink.images.centroid import screen

    half = _bank_half_px(sigma_px) + math.ceil(3.0 * sigma_px) + 1
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    profiles, norms = _bank_profiles(sigma_px)
    kernels = [
        np.outer(pa, pb) / (na * nb)
        for pa, na in zip(profiles, norms, strict=True)
        for pb, nb in zip(profiles, norms, strict=True)
    ]
    out = []
    for dy in screen._PHASES_PX:
        py = pixel_integrated_gaussian(offsets, dy, sigma_px)
        for dx in screen._PHASES_PX:
            star = np.outer(py, pixel_integrated_gaussian(offsets, dx, sigma_px))
            out.append(max(float(np.max(ndimage.correlate(star, k, mode="constant"))) for k in kernels))
    return np.array(out)
