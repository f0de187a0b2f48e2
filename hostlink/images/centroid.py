"""Star centroids from images (issue 11, ``hostlink centroid``): images -> a session of unidentified stars
(``star_id`` 0), with the source extraction of SEP (Barbary 2016, JOSS 1:58: the Source Extractor algorithms of
Bertin & Arnouts 1996 as a library).

Per image:

1. subtract a given dark or median frame (a median of night-sky frames taken at different pointings removes the
   fixed pattern: hot pixels, amplifier glow, vignetted sky), then SEP's spatially varying background
   (``sep.Background``, a 64 px mesh, 3 x 3 median filter) and its noise map, corrected to what the detection
   filter actually sees, box by box (:func:`hostlink.images.background.filtered_noise_correction`: clipped, skewed
   or correlated noise, a glow or a gradient that raises it in one part of the frame), with the blank regions (a
   saturated glow) masked and the residual of a sharp edge (a horizon) removed (docs/realsky.md);
2. detect: SEP's matched-filter detection (``sep.extract``) at ``threshold_sigma`` x the local noise with a minimum
   footprint (default 2: SEP counts the footprint's pixels that are themselves above the threshold, and a sharp
   faint star has 1-2; 3 lost 5 of the stars the plate solver names on the granasat frames; 1 keeps 5 more of them,
   but lets the heavy tail of clipped, correlated 8-bit noise through: 18 false detections per 1.3 Mpx in the test
   of it), its multi-threshold deblending (32 levels, contrast 0.005), without SEP's cleaning (it merged sharp stars
   of 8-16 sigma into bright neighbours 8-18 px away: :data:`_SEP_CLEAN`);
3. reject, each counted: a *hot pixel* (a single bright pixel explains the detection better than a star of the
   frame's measured PSF, by a likelihood-ratio test, :func:`_hot_pixels`: a sharp star passes, however little of its
   flux its neighbours hold), *blended* (SEP's ``OBJ_MERGED`` flag: deblended from a neighbour within
   :data:`_BLEND_CLEAR_SIGMAS` PSF sigmas; or Gaussian-windowed second moments more elongated than the PSF of the
   star's own part of the field, :func:`_unresolved_pairs`, :func:`_psf_ellipticity_field`: two stars closer than the
   deblender can split), *edge* (footprint truncated by the image border, ``OBJ_TRUNC``, and saturated, or its PSF
   fit not taken: an unsaturated star the border cuts is fitted on the pixels it has), *without flux* (no positive
   PSF flux: noise); a *saturated* star (a pixel of the footprint at the image's clip level) is kept, flagged and
   counted (``keep_saturated``, the default: the brightest stars are the anchors of identification), or rejected and
   counted;
4. centroid: SEP's windowed centroid (``sep.winpos``, Source Extractor's XWIN_IMAGE: the iterated Gaussian-weighted
   first moment, which converges to the maximum of the image correlated with the window) with the window sigma
   equal to the frame's PSF sigma (the median over its most significant stars of the half-light radius / 1.1774,
   the Gaussian's r50 = sigma sqrt(2 ln 2)): the matched filter, maximum likelihood where background and read noise
   dominate, but (4/3)^2 x the Cramer-Rao variance where the star's own shot noise does. It starts the default
   ``psf-fit``: a weighted least-squares fit of the pixel-integrated Gaussian PSF (:func:`psf_model`; position, flux
   and local background free, sigma fixed at the frame's: the width of that model fitted to the same stars,
   :func:`_psf_model_sigma_px`, as r50's is the pixel-convolved star's, 17 % wide at 0.77 px) with the weights of
   shot + read noise when the gain is known, every star of the frame at once (:func:`_levenberg_marquardt_batch`,
   in numpy): maximum likelihood at every signal-to-noise ratio (measured at 0.99-1.03 x the bound from peak SNR
   15 to 250, :func:`centroid_crb_px`, tests/test_images_centroid.py);
5. noise: each star's 1-sigma centroid noise per axis ``sigma_px``, the Cramer-Rao bound of its centroid
   (:func:`centroid_sigma_px`, :func:`centroid_crb_px`) from its flux, the local noise and the PSF: the fit reaches
   it (step 4), so it is each star's weight in the calibration;
6. flux: the linear least-squares amplitude of the pixel-integrated Gaussian PSF (the renderer's model,
   :func:`hostlink.sky.render.pixel_integrated_gaussian`) at the centroid, F = sum (I - b) P / sum P^2 over +-3 PSF
   sigmas [ADU, the star's total flux], with b the local background (median of the surrounding ring: it removes what
   the mesh background leaves, e.g. on skewed noise clipped at zero): the maximum-likelihood flux where background
   noise dominates, so stars rank by signal-to-noise, not by how much noise an aperture collects; instrumental
   magnitude ``mag = -2.5 log10(flux_adu)`` (no zero point: it orders stars, brightest first).
7. candidates (``candidate_sigma``, default 3; None, or not below ``threshold_sigma``: none): the local maxima of
   the filtered image outside every detection's footprint, clear of the kept stars, centroided by the window and
   kept when their PSF-fit flux is at least ``candidate_sigma`` x its noise (:func:`_candidates`). They hold faint
   stars below the threshold, stars the extraction loses otherwise, and mostly noise. The session carries them
   after the frame's stars with their significance in the ``snr`` column (empty on detected stars); identification
   never uses them, and names one only where the calibrated camera predicts a catalogue star
   (:mod:`hostlink.images.guided`).

SEP and this module use the camera-model pixel convention (docs/camera-model.md): ``(0, 0)`` is the centre of the
first (top-left) pixel, ``x`` the column, ``y`` the row.

Time of each image (exposure mid-time, UTC): one of ``TimeOptions`` (a time for every image, a list per image, a
strptime pattern on the file name, a date with the time of day unknown, or no time), else the file's metadata
(:mod:`hostlink.images.read`); an image with no known time is a one-line error naming it.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hostlink.errors import UserError, one_line
from hostlink.files.session import Session
from hostlink.files.times import parse_iso_utc_many
from hostlink.images.background import filtered_noise_correction, saturated_regions
from hostlink.images.read import RawImage, read_image
from hostlink.sky.render import pixel_integrated_gaussian, pixel_integrated_gaussian_dsource

#: r50 / sigma of a circular Gaussian: sqrt(2 ln 2).
_R50_PER_SIGMA = math.sqrt(2.0 * math.log(2.0))
#: The PSF flux is fitted over +-this many PSF sigmas (+1 px) around the centroid; the local background is the median
#: of the ring from there out to 3 px farther.
_PSF_FIT_SIGMAS = 3.0
_RING_WIDTH_PX = 3
#: Stars (the most significant kept) over which the frame's PSF sigma is the median: few, as a noisy frame may hold
#: only a dozen real stars among its detections.
_PSF_STARS = 10
#: The PSF sigma is iterated from this start [px], each time measuring r50 within this many sigmas (99.97 % of a
#: Gaussian's flux lies within 4 sigma; a larger radius only adds background noise to r50).
_DEFAULT_PSF_SIGMA_PX = 1.0
_PSF_RMAX_SIGMAS = 4.0
_PSF_ITERATIONS = 3
#: Smallest PSF sigma the window may take [px] (SEP's own floor for winpos, 2 / 2.35 x 0.5 = 0.43 px, rounded).
_MIN_PSF_SIGMA_PX = 0.45
#: A windowed centroid that moves farther than this from the isophotal one [px] has failed (a neighbour pulled it).
_WINPOS_MAX_SHIFT_PX = 2.0
#: An ellipticity is significant beyond this many standard deviations of its noise (a round star exceeds it with
#: probability exp(-16 / 2) = 3e-4: the ellipticity's two components are Gaussian with that deviation).
_ELLIPTICITY_SIGNIFICANCE = 4.0
#: The detection filter (SEP's default 3 x 3 kernel, a Gaussian of sigma ~1 px sampled on pixels).
_FILTER_KERNEL = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]], dtype=np.float32)
#: ``--median-of-inputs`` is refused when the median frame itself holds this many star-like sources (and as many as a
#: frame keeps): the images then share a pointing.
_MEDIAN_MAX_STARS = 5
#: A PSF fit that moves the centroid farther than this from the windowed one [px] has failed (a neighbour, noise).
_FIT_MAX_SHIFT_PX = 1.0
#: Centroid methods: the PSF fit (maximum likelihood, the default) or SEP's windowed centroid alone.
CENTROID_METHODS = ("psf-fit", "window")
#: Well-measured stars needed to take the frame's PSF shape from them (else the PSF is taken as round).
_PSF_SHAPE_STARS = 5
#: ... whose ellipticity is known to this standard deviation.
_PSF_SHAPE_MAX_SIGMA = 0.1
#: Floor of a saturated star's ``sigma_px`` [px]: its clipped core carries no PSF-fit information and its windowed
#: centroid follows the core's asymmetries: measured 0.33 px per axis over the 446 saturated stars of the granasat
#: JPEG frames after calibration, against 0.19 px for their unsaturated stars (docs/realsky.md).
SATURATED_SIGMA_PX = 0.3
#: SEP's buffers: a noisy frame at a low threshold can hold many more pixels above threshold than SEP's default.
_SEP_PIXSTACK = 3_000_000
#: SEP's cleaning (Source Extractor's CLEAN: a detection its bright neighbour's modelled wing could explain is merged
#: into it) is off: on the granasat frames it removed sharp stars of 8-16 sigma 8-18 px from a bright one (the
#: stars the plate solver names; found with it off, at the same threshold and footprint). What cleaning guards
#: against, bumps on a bright star's wing, the blend test and the PSF fit's flux see.
_SEP_CLEAN = False
_SEP_SUB_OBJECTS = 4096


#: Default minimum footprint [filtered pixels above the threshold] (module docstring, step 2).
_DEFAULT_MIN_AREA_PX = 2
#: Default significance down to which candidates are written (module docstring, step 7): the PSF-fit flux over its
#: noise. Candidates only name a star where the calibrated camera predicts one (:mod:`hostlink.images.guided`, which
#: states the chance that noise meets a prediction); below 3 the noise peaks of a frame grow ~10 x per sigma.
DEFAULT_CANDIDATE_SIGMA = 3.0


@dataclass(frozen=True)
class CentroidOptions:
    """How to centroid. ``threshold_sigma``: detection threshold in units of the local background noise;
    ``min_area_px``: minimum footprint [px] above threshold; ``dark`` / ``median``: a frame to subtract first (a file);
    ``median_of_inputs``: subtract the per-pixel median of all the images given (they must be taken at different
    pointings, at least 3); ``saturation_adu``: the clip level (default: from the file, the integer type's maximum);
    ``psf_sigma_px``: the centroid window (default: measured per frame); ``hot_pixel_chi2``, ``max_ellipticity``:
    rejection limits (module docstring, :func:`_hot_pixels`); ``gain_e_per_adu``: the detector's gain, when known, adds
    the stars' own shot noise to the weights of the PSF fit (without it: 1.13-1.17 x the bound instead of 1.0 for stars
    whose shot noise dominates), to ``sigma_px`` and to the noise of the blend test (without it the test counts
    background noise only and rejects about 1 % of moderately bright single stars); ``background_box_px``: SEP's
    background mesh; ``max_stars``: keep the brightest N per image (None: all); ``method``: ``psf-fit`` (default) or
    ``window`` (:data:`CENTROID_METHODS`); ``keep_saturated`` (default True): keep saturated stars (the brightest stars
    of a frame, the anchors of every pattern matcher: an 8-bit camera saturates its brightest stars in most exposures)
    with a windowed centroid (a clipped core does not follow the PSF), ranked first, flagged in the ``saturated`` column
    with a ``sigma_px`` of at least :data:`SATURATED_SIGMA_PX`, counted in ``FrameReport.saturated_kept``; False rejects
    them."""

    threshold_sigma: float = 5.0
    min_area_px: int = _DEFAULT_MIN_AREA_PX
    dark: str | Path | None = None
    median: str | Path | None = None
    median_of_inputs: bool = False
    saturation_adu: float | None = None
    psf_sigma_px: float | None = None
    hot_pixel_chi2: float = 25.0
    max_ellipticity: float = 0.1
    keep_saturated: bool = True
    gain_e_per_adu: float | None = None
    method: str = "psf-fit"
    background_box_px: int = 64
    max_stars: int | None = None
    candidate_sigma: float | None = DEFAULT_CANDIDATE_SIGMA


@dataclass(frozen=True)
class TimeOptions:
    """Where the time of each image comes from (at most one; none: the files' metadata). ``time_utc``: one ISO UTC
    time for every image; ``times_file``: a text file, one line per image, ``NAME,TIME`` or ``NAME TIME`` (NAME the
    image's file name, TIME ISO UTC; ``#`` starts a comment); ``time_pattern``: a ``datetime.strptime`` pattern
    matching the whole file name or its stem (UTC unless it has ``%z``); ``date``: ``YYYY-MM-DD``, the UTC date with
    the time of day unknown (12:00:00 UTC is written: within 12 h of any time of that day, which moves annual
    aberration by at most 0.18", docs/file-formats.md); ``time_unknown``: no time (every ``t_utc`` empty)."""

    time_utc: str | None = None
    times_file: str | Path | None = None
    time_pattern: str | None = None
    date: str | None = None
    time_unknown: bool = False


@dataclass
class FrameReport:
    """What happened to one image: detections, the stars kept and every rejection by reason (``rejected_no_flux``: a
    detection whose PSF-fit flux is not positive, noise), the background noise [ADU], the PSF sigma used [px], the time
    and its source."""

    path: str
    detected: int = 0
    kept: int = 0
    rejected_hot: int = 0
    rejected_saturated: int = 0
    saturated_kept: int = 0
    rejected_blended: int = 0
    rejected_edge: int = 0
    rejected_no_flux: int = 0
    candidates: int = 0
    background_rms_adu: float = float("nan")
    psf_sigma_px: float = float("nan")
    time_utc: str = ""
    time_source: str = ""


@dataclass
class Detections:
    """The stars kept in one image, brightest first: centroid [px] (camera convention), flux [ADU], instrumental
    magnitude; ``report`` the counts; ``sigma_px`` each centroid's 1-sigma noise per axis [px]
    (:func:`centroid_sigma_px`); ``saturated`` True for a kept saturated star."""

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    mag: np.ndarray
    report: FrameReport = field(default_factory=lambda: FrameReport(path=""))
    sigma_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    saturated: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    candidates: Candidates | None = None


@dataclass(frozen=True)
class Candidates:
    """Faint candidates of one image (module docstring, step 7), most significant first: centroid [px], PSF-fit flux
    [ADU], instrumental magnitude, ``sigma_px`` and ``snr`` (the PSF-fit flux over its noise)."""

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    mag: np.ndarray
    sigma_px: np.ndarray
    snr: np.ndarray


@dataclass
class CentroidResult:
    """The session (one frame per image, in time order; ``star_id`` 0; extra columns ``flux_adu``, ``sigma_px`` (each
    centroid's 1-sigma noise per axis [px], :func:`centroid_sigma_px`), ``saturated`` (1 for a kept saturated star),
    ``image``, ``time_source``) and one :class:`FrameReport` per frame."""

    session: Session
    frames: list[FrameReport]


# ----------------------------------------------------------------------------------------------------------------
# one image


def centroid_pixels(
    pixels: np.ndarray,
    options: CentroidOptions = CentroidOptions(),
    background: np.ndarray | None = None,
    saturation_adu: float | None = None,
) -> Detections:
    """Detect and centroid the stars of one image ``pixels[row, column]`` [ADU] (module docstring, steps 1-6), stage
    by stage: :func:`_extract` (background, noise, detection), :func:`_screen` (rejections before centroiding),
    :func:`_centroid_screened` (centroids, unresolved pairs, the PSF fit), :func:`_measured` (fluxes, ``sigma_px``,
    order). ``background``: a dark or median frame to subtract first; ``saturation_adu``: the clip level of ``pixels``
    (``options.saturation_adu`` wins; None: no saturation test)."""
    _check_options(options)
    raw = np.ascontiguousarray(pixels, dtype=np.float64)
    level = options.saturation_adu if options.saturation_adu is not None else saturation_adu
    blank = saturated_regions(raw, level)
    sub, rms, filtered, objects, segmap = _extract(_less_background_frame(raw, background), options, blank)
    report = FrameReport(path="", detected=int(objects.size), background_rms_adu=float(np.median(rms[~blank])))
    if objects.size == 0:
        return _no_stars(report)
    screen = _screen(sub, rms, raw, objects, segmap, options, level)
    report.rejected_saturated = 0 if options.keep_saturated else int(screen.saturated.sum())
    report.rejected_hot = int(screen.hot.sum())
    report.rejected_blended = int(screen.blended.sum())
    report.rejected_edge = int(screen.edge.sum())
    good = objects[screen.keep]
    if good.size == 0:
        return _no_stars(report)
    stars = _centroid_screened(
        sub, rms, good, screen.saturated[screen.keep], screen.fit_at_edge[screen.keep], options, report
    )
    if stars is None:
        return _no_stars(report)
    detections = _measured(sub, rms, *stars, options, report)
    fainter = options.candidate_sigma is not None and options.candidate_sigma < options.threshold_sigma
    if fainter and detections.x_px.size:  # candidates are what lies below the detection threshold
        detections.candidates = _candidates(sub, rms, filtered, segmap, detections, report.psf_sigma_px, options)
        report.candidates = int(detections.candidates.x_px.size)
    return detections


#: A candidate's peak lies at least this far [px] from every kept star, in PSF sigmas plus 1 px (the fit's stamp,
#: :data:`_PSF_FIT_SIGMAS`: nearer, a star's wing and the candidate share pixels).
_CANDIDATE_CLEAR_SIGMAS = _PSF_FIT_SIGMAS


def _candidates(sub, rms, filtered, segmap, kept: Detections, sigma: float, options: CentroidOptions) -> Candidates:
    """Module docstring, step 7: faint candidates, the local maxima of the filtered image outside every detection's
    footprint (below the threshold, or lost by the extraction) and clear of the kept stars, centroided by
    the window of the PSF's width (:func:`_window_iterated`: where the background's noise dominates, as it does for
    every faint star, the matched filter, the maximum-likelihood centroid) and kept when their PSF-fit flux F is at
    least ``candidate_sigma`` x its noise: snr = F sqrt(sum P^2) / rms (:func:`_snr`). Most are noise, and they are
    not tested for hot pixels: :mod:`hostlink.images.guided` names one only where the calibrated camera predicts a
    catalogue star as bright, and states the chance of that for noise, counting every candidate (hot pixels too)."""
    rows, cols = _local_maxima(filtered / (rms * _FILTERED_NOISE_PER_PX), options.candidate_sigma, segmap)
    x0, y0 = cols.astype(np.float64), rows.astype(np.float64)
    clear = _CANDIDATE_CLEAR_SIGMAS * sigma + 1.0
    if kept.x_px.size and x0.size:
        from scipy.spatial import cKDTree

        near, _ = cKDTree(np.column_stack([kept.x_px, kept.y_px])).query(np.column_stack([x0, y0]))
        x0, y0, rows, cols = x0[near > clear], y0[near > clear], rows[near > clear], cols[near > clear]
    x, y = _in_chunks(_WINDOW_HALF_SIGMAS * 2, x0.size, lambda k: _window_iterated(sub, x0[k], y0[k], sigma))
    flux = _psf_fluxes(sub, x, y, sigma)
    snr = _snr(sub, rms, x, y, sigma, flux)
    keep = np.flatnonzero(snr >= options.candidate_sigma)
    keep = keep[np.argsort(-snr[keep], kind="stable")]
    x, y, flux, snr = x[keep], y[keep], flux[keep], snr[keep]
    sigma_px = centroid_sigma_px(x, y, flux, rms, sigma, options.gain_e_per_adu)
    stated = _noise_stated(sigma_px)  # a row without a centroid noise is not written
    x, y, flux, sigma_px, snr = x[stated], y[stated], flux[stated], sigma_px[stated], snr[stated]
    return Candidates(x, y, flux, -2.5 * np.log10(flux), sigma_px, snr)


#: The candidates' window: iterations, and the stamp's half-width in window sigmas (+1 px).
_WINDOW_ITERATIONS = 8
_WINDOW_HALF_SIGMAS = 4


def _window_iterated(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Source Extractor's windowed centroid (XWIN_IMAGE, Bertin's SExtractor manual, "windowed positional
    parameters") of every star at once: x <- x + 2 sum w I (x_i - x) / sum w I with the Gaussian window
    w = exp(-r^2 / (2 sigma^2)) over +-(4 sigma + 1) px, :data:`_WINDOW_ITERATIONS` times (as ``sep.winpos`` does for
    one star at a time); a star whose step leaves the stamp, or whose windowed flux is not positive, keeps its
    start."""
    half = int(math.ceil(_WINDOW_HALF_SIGMAS * sigma_px)) + 1
    cols, rows, data, _ = _stamps(sub, x, y, half)
    cx, cy = x.copy(), y.copy()
    ok = np.ones(x.size, dtype=bool)
    for _ in range(_WINDOW_ITERATIONS):
        dx = cols - cx[:, None]
        dy = rows - cy[:, None]
        wx = np.exp(-0.5 * (dx / sigma_px) ** 2)
        wy = np.exp(-0.5 * (dy / sigma_px) ** 2)
        wi = wy[:, :, None] * wx[:, None, :] * data
        total = np.sum(wi, axis=(1, 2))
        ok &= total > 0
        safe = np.where(ok, total, 1.0)
        cx = cx + np.where(ok, 2.0 * np.sum(wi * dx[:, None, :], axis=(1, 2)) / safe, 0.0)
        cy = cy + np.where(ok, 2.0 * np.sum(wi * dy[:, :, None], axis=(1, 2)) / safe, 0.0)
        ok &= (np.abs(cx - x) <= _WINPOS_MAX_SHIFT_PX) & (np.abs(cy - y) <= _WINPOS_MAX_SHIFT_PX)
    return np.where(ok, cx, x), np.where(ok, cy, y)


#: The filtered image's noise per unit of the per-pixel noise (the detection kernel normalised: sqrt(sum k^2)).
_FILTERED_NOISE_PER_PX = math.sqrt(float(np.sum((_FILTER_KERNEL / _FILTER_KERNEL.sum()) ** 2)))


def _local_maxima(significance: np.ndarray, limit: float, segmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels of ``significance`` at least ``limit``, outside every footprint (``segmap`` 0),
    at least :data:`_HOT_BOX_HALF_PX` from the border, and not below any of their 8 neighbours."""
    h, w = significance.shape
    m = _HOT_BOX_HALF_PX
    inner = significance[m : h - m, m : w - m]
    rows, cols = np.nonzero((inner >= limit) & (segmap[m : h - m, m : w - m] == 0))
    rows, cols = rows + m, cols + m
    value = significance[rows, cols]
    peak = np.ones(rows.size, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= value >= significance[rows + dr, cols + dc]
    return rows[peak], cols[peak]


def _snr(sub, rms, x: np.ndarray, y: np.ndarray, sigma_px: float, flux: np.ndarray | None = None) -> np.ndarray:
    """Signal-to-noise ratio of the PSF-fit flux at (x, y): F sqrt(sum P^2) / rms (:func:`_candidates`); ``flux``
    when already measured."""
    if x.size == 0:
        return np.zeros(0)
    if flux is None:
        flux = _psf_fluxes(sub, x, y, sigma_px)
    h, w = rms.shape
    r = np.clip(np.rint(y).astype(np.int64), 0, h - 1)
    c = np.clip(np.rint(x).astype(np.int64), 0, w - 1)
    return flux * np.sqrt(_psf_sum_squares(x, y, sigma_px)) / rms[r, c]


def _psf_sum_squares(x: np.ndarray, y: np.ndarray, sigma_px: float) -> np.ndarray:
    """sum P^2 of the pixel-integrated Gaussian PSF at each (x, y) over +-(3 sigma + 1) px (the flux fit's stamp,
    :func:`_psf_fluxes`): the flux's noise is rms / sqrt(sum P^2) for white noise. Separable: (sum Px^2)(sum Py^2)."""
    half = int(math.ceil(_PSF_FIT_SIGMAS * sigma_px)) + 1
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    cols = np.rint(x)[:, None] + offsets[None, :]
    rows = np.rint(y)[:, None] + offsets[None, :]
    px = pixel_integrated_gaussian(cols, x[:, None], sigma_px)
    py = pixel_integrated_gaussian(rows, y[:, None], sigma_px)
    return np.sum(px * px, axis=1) * np.sum(py * py, axis=1)


def _no_stars(report: FrameReport) -> Detections:
    """The :class:`Detections` of a frame that keeps no star."""
    return Detections(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), report, np.zeros(0), np.zeros(0, bool))


def _less_background_frame(raw: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """``raw`` less the dark or median frame ``background`` (a copy; a frame of another size is a UserError)."""
    if background is None:
        return raw.copy()
    if background.shape != raw.shape:
        raise UserError(
            f"background frame is {background.shape[1]} x {background.shape[0]} px, image is "
            f"{raw.shape[1]} x {raw.shape[0]} px"
        )
    return raw - background


def _extract(data: np.ndarray, options: CentroidOptions, blank: np.ndarray | None = None):
    """Module docstring, steps 1-2: SEP's background mesh subtracted (``blank``, the blank regions of
    :func:`hostlink.images.background.saturated_regions`, masked from it and from the detection), its noise map
    corrected to what the detection filter sees, box by box (:func:`hostlink.images.background.
    filtered_noise_correction`), then SEP's matched-filter detection and deblending. Returns the
    background-subtracted image, the noise map [ADU], the image filtered by the detection kernel, SEP's objects and its
    segmentation map."""
    import sep

    box = int(min(options.background_box_px, max(8, min(data.shape) // 2)))
    sep.set_extract_pixstack(_SEP_PIXSTACK)
    sep.set_sub_object_limit(_SEP_SUB_OBJECTS)
    try:
        blank = np.zeros(data.shape, dtype=bool) if blank is None else blank
        bkg = sep.Background(data, mask=blank, bw=box, bh=box, fw=3, fh=3)
        sub = data - bkg.back()
        offset, rms, filtered, ignored = filtered_noise_correction(
            sub, bkg.rms(), _FILTER_KERNEL, box, blank, bkg.globalback
        )
        sub -= offset
        objects, segmap = sep.extract(
            sub,
            options.threshold_sigma,
            err=rms,
            mask=ignored,
            minarea=options.min_area_px,
            filter_kernel=_FILTER_KERNEL,
            deblend_nthresh=32,
            deblend_cont=0.005,
            clean=_SEP_CLEAN,
            segmentation_map=True,
        )
    except Exception as exc:  # SEP reports buffer overflows as plain exceptions
        raise UserError(f"source extraction failed ({one_line(exc)}); raise --threshold-sigma") from None
    return sub, rms, filtered, objects, segmap


@dataclass(frozen=True)
class _Screen:
    """The rejections before centroiding (module docstring, step 3), (N,) bool over SEP's objects: ``keep``, and each
    rejection counted once, in order (saturated only when not kept, hot, blended, edge); ``saturated``: a raw pixel
    of the footprint at the clip level (kept or not); ``fit_at_edge``: cut by the border, kept while its PSF fit
    converges."""

    keep: np.ndarray
    saturated: np.ndarray
    hot: np.ndarray
    blended: np.ndarray
    edge: np.ndarray
    fit_at_edge: np.ndarray


def _screen(sub, rms, raw, objects, segmap, options: CentroidOptions, level: float | None) -> _Screen:
    """Module docstring, step 3, before any centroid: edge, saturated, hot pixels and deblended neighbours."""
    import sep

    # edge: the footprint touches the border (its centroid is biased)
    edge = (objects["flag"] & sep.OBJ_TRUNC) != 0
    # saturated: a raw pixel of the footprint at the clip level
    saturated = np.zeros(objects.size, bool)
    if level is not None:
        labelled = segmap > 0
        peak_raw = np.full(objects.size + 1, -np.inf)
        np.maximum.at(peak_raw, segmap[labelled], raw[labelled])
        saturated = peak_raw[1:] >= level
    blended = (objects["flag"] & sep.OBJ_MERGED) != 0
    # hot pixels: the frame's PSF measured first on the detections that are neither single-pixel spikes by a coarse
    # screen nor clipped, then every detection tested against it (a sharp star passes, a spike does not)
    psf_hot = options.psf_sigma_px
    if psf_hot is None:
        screened = ~_single_pixel_spikes(sub, objects) & ~saturated & ~edge & ~blended
        psf_hot = _frame_psf_sigma_px(sub, objects[screened] if np.any(screened) else objects)
    hot = _hot_pixels(sub, rms, objects, psf_hot, options.hot_pixel_chi2) & ~saturated
    # a deblended star whose neighbours all lie beyond the PSF fit's reach is measured as a single one
    blended &= _nearest_neighbour_px(objects["x"], objects["y"], blended) <= _BLEND_CLEAR_SIGMAS * psf_hot
    # a star cut by the border: the PSF fit uses the pixels there are (unbiased); the window cannot (a clipped core);
    # only where the hot-pixel test saw the whole box around its brightest pixel (nearer the border it cannot judge)
    h, w = sub.shape
    judged = (
        (objects["xpeak"] >= _HOT_BOX_HALF_PX)
        & (objects["xpeak"] <= w - 1 - _HOT_BOX_HALF_PX)
        & (objects["ypeak"] >= _HOT_BOX_HALF_PX)
        & (objects["ypeak"] <= h - 1 - _HOT_BOX_HALF_PX)
    )
    fit_at_edge = edge & ~saturated & judged & (options.method == "psf-fit")
    edge &= ~fit_at_edge
    keep = np.ones(objects.size, bool)
    rejected_saturated = saturated.copy() if not options.keep_saturated else np.zeros(objects.size, bool)
    for mask in (rejected_saturated, hot, blended, edge):
        mask &= keep
        keep &= ~mask
    return _Screen(keep, saturated, hot, blended, edge, fit_at_edge)


def _centroid_screened(sub, rms, good, clipped, truncated, options: CentroidOptions, report: FrameReport):
    """Module docstring, step 4, on the screened objects ``good`` (``clipped``: saturated, ``truncated``: cut by the
    border): the frame's PSF sigma, windowed centroids, the unresolved pairs rejected (counted as blended), then the
    PSF fit (a border-cut star whose fit is not taken is rejected at the edge). Returns (x, y, SEP objects, clipped,
    PSF sigma [px]) of the stars kept, or None when none is."""
    sigma = options.psf_sigma_px or _frame_psf_sigma_px(sub, good[~clipped] if np.any(~clipped) else good)
    x, y = _windowed_centroids(sub, good, sigma)
    # unresolved pairs (too close for a saddle between them: the deblender sees one peak) are elongated beyond the PSF
    # of their part of the field; a clipped core's shape is not the PSF's (round where the PSF is trailed): saturated
    # stars are neither tested nor part of the PSF's shape
    ellipticity, ellipticity_sigma = _windowed_ellipticity(sub, rms, x, y, sigma, options.gain_e_per_adu)
    ellipticity_sigma[clipped | truncated] = np.inf  # a border cuts a star's moments too
    unresolved = _unresolved_pairs(ellipticity, ellipticity_sigma, options.max_ellipticity, x, y, sub.shape)
    report.rejected_blended += int(unresolved.sum())
    good, clipped, truncated = good[~unresolved], clipped[~unresolved], truncated[~unresolved]
    if good.size == 0:
        return None
    first = sigma
    if options.psf_sigma_px is None and np.any(unresolved):  # the pairs widened the first estimate
        sigma = _frame_psf_sigma_px(sub, good[~clipped] if np.any(~clipped) else good)
    if sigma != first:  # each star's window is its own: with the same sigma, the same centroids
        x, y = _windowed_centroids(sub, good, sigma)
    else:
        x, y = x[~unresolved], y[~unresolved]
    if options.psf_sigma_px is None:  # the PSF model's own width (pixel-integrated): the fit, flux and sigma_px
        sigma = _psf_model_sigma_px(sub, good[~clipped] if np.any(~clipped) else good, sigma)
    report.psf_sigma_px = float(sigma)
    if options.method == "psf-fit":  # a clipped core does not follow the PSF: saturated stars keep the window
        fit = np.flatnonzero(~clipped)
        x[fit], y[fit], fitted = _psf_fit_centroids(sub, rms, x[fit], y[fit], sigma, options.gain_e_per_adu)
        lost = np.zeros(x.size, dtype=bool)
        lost[fit[~fitted]] = True
        lost &= truncated  # a star cut by the border with no converged fit: its windowed centroid is biased
        report.rejected_edge += int(lost.sum())
        x, y, good, clipped = x[~lost], y[~lost], good[~lost], clipped[~lost]
    return x, y, good, clipped, float(sigma)


def _measured(sub, rms, x, y, good, clipped, sigma: float, options: CentroidOptions, report: FrameReport) -> Detections:
    """Module docstring, steps 5-6: each star's PSF flux (a detection without flux rejected), ``sigma_px`` and
    instrumental magnitude, brightest first (the brightest ``max_stars``)."""
    flux = _psf_fluxes(sub, x, y, sigma)
    # the PSF amplitude of a clipped star is too low; its isophotal sum is a lower bound that keeps it first
    flux[clipped] = np.maximum(flux[clipped], good["flux"][clipped])
    # no flux where the PSF sits: noise that crossed the threshold (no star, and no centroid noise to state)
    measured = flux > 0
    report.rejected_no_flux = int(np.count_nonzero(~measured))
    x, y, flux, clipped = x[measured], y[measured], flux[measured], clipped[measured]
    report.saturated_kept = int(clipped.sum())
    sigma_px = centroid_sigma_px(x, y, flux, rms, sigma, options.gain_e_per_adu)
    sigma_px[clipped] = np.maximum(sigma_px[clipped], SATURATED_SIGMA_PX)
    # no noise measured where the star sits (every pixel around it clipped): no sigma_px, so no row
    stated = _noise_stated(sigma_px)
    report.rejected_no_flux += int(np.count_nonzero(~stated))
    report.saturated_kept = int(clipped[stated].sum())
    x, y, flux, clipped, sigma_px = x[stated], y[stated], flux[stated], clipped[stated], sigma_px[stated]
    order = np.argsort(-flux, kind="stable")
    if options.max_stars is not None:
        order = order[: options.max_stars]
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(flux > 0, -2.5 * np.log10(np.where(flux > 0, flux, 1.0)), np.nan)
    report.kept = int(order.size)
    return Detections(x[order], y[order], flux[order], mag[order], report, sigma_px[order], clipped[order])


def _noise_stated(sigma_px: np.ndarray) -> np.ndarray:
    """(N,) bool: ``sigma_px`` is a finite positive number (every row written carries one: calibrate weighs by it)."""
    return np.isfinite(sigma_px) & (sigma_px > 0)


def _check_options(options: CentroidOptions) -> None:
    if not (math.isfinite(options.threshold_sigma) and options.threshold_sigma > 0):
        raise UserError(f"threshold-sigma must be a number > 0, got {options.threshold_sigma!r}")
    if options.min_area_px < 1:
        raise UserError(f"minimum area must be >= 1 px, got {options.min_area_px}")
    if options.psf_sigma_px is not None and not (options.psf_sigma_px > 0):
        raise UserError(f"psf sigma must be > 0 px, got {options.psf_sigma_px!r}")
    if options.gain_e_per_adu is not None and not (options.gain_e_per_adu > 0):
        raise UserError(f"gain must be > 0 e-/ADU, got {options.gain_e_per_adu!r}")
    if options.method not in CENTROID_METHODS:
        raise UserError(f"centroid method must be one of {', '.join(CENTROID_METHODS)}, got {options.method!r}")
    if options.candidate_sigma is not None and not (
        math.isfinite(options.candidate_sigma) and options.candidate_sigma > 0
    ):
        raise UserError(f"candidate-sigma must be a number > 0, got {options.candidate_sigma!r}")
    if options.max_stars is not None and options.max_stars < 1:
        raise UserError(f"max-stars must be >= 1, got {options.max_stars}")


#: Coarse screen for single-pixel spikes, used only to choose the stars the frame's PSF is measured on: the mean of
#: the 4 edge neighbours of the brightest pixel below this fraction of it (a pixel-integrated Gaussian of sigma s has
#: at least [Phi(1.5/s) - Phi(0.5/s)] / [2 Phi(0.5/s) - 1]: 0.23 at s = 0.5 px, 0.60 at s = 1 px).
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


#: A deblended detection is measured as a single star when every other detection lies farther than this many PSF
#: sigmas: the PSF fit's stamp reaches 3 sigma + 1 px, and a neighbour's light 3 sigma beyond that is < 1 % of its
#: peak.
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
    projector onto the m-th span is U[:, m] U[:, m]^T."""
    return np.stack([np.linalg.qr(a)[0] for a in columns], axis=1)


def _hot_pixels(sub: np.ndarray, rms: np.ndarray, objects: np.ndarray, psf_sigma_px: float, chi2_limit: float):
    """Hot pixels: detections that a single bright pixel explains better than a star of the frame's own PSF, by a
    likelihood-ratio test. Over the (2h+1)^2 pixels d around the brightest one (h = :data:`_HOT_BOX_HALF_PX`), in
    units of the local noise, two linear models each with a flat background: a spike (amplitude on the central pixel
    only) and the pixel-integrated Gaussian of sigma ``psf_sigma_px`` (:func:`hostlink.sky.render.
    pixel_integrated_gaussian`) at the best of a 5 x 5 grid of sub-pixel positions and of three widths from
    :data:`_HOT_SHARPEST_FRACTION` of it to all of it; chi^2 = |d|^2 - d^T Q d for each
    model's projector Q. A detection is a hot pixel when chi^2_star - chi^2_spike > ``chi2_limit``: the star model is
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
    c = np.clip(objects["xpeak"].astype(np.int64), half, w - 1 - half)
    r = np.clip(objects["ypeak"].astype(np.int64), half, h - 1 - half)
    offsets = np.arange(-half, half + 1)
    cut = sub[r[:, None, None] + offsets[None, :, None], c[:, None, None] + offsets[None, None, :]]
    d = cut.reshape(objects.size, -1) / np.maximum(rms[r, c], 1e-12)[:, None]
    flat = np.ones(offsets.size**2)
    spike = np.zeros(offsets.size**2)
    spike[spike.size // 2] = 1.0
    widths = np.geomspace(max(_MIN_PSF_SIGMA_PX, _HOT_SHARPEST_FRACTION * psf_sigma_px), psf_sigma_px, 3)
    stars = [
        np.outer(pixel_integrated_gaussian(offsets, dy, width), pixel_integrated_gaussian(offsets, dx, width)).ravel()
        for width in widths
        for dy in _HOT_POSITIONS_PX
        for dx in _HOT_POSITIONS_PX
    ]
    basis = _orthonormal_bases([np.column_stack([m, flat]) for m in [spike, *stars]])
    # d^T Q d = |U^T d|^2 for the projector Q = U U^T of each model (U: an orthonormal basis of its 2 columns)
    explained = np.sum((d @ basis.reshape(d.shape[1], -1)).reshape(objects.size, -1, 2) ** 2, axis=2)
    total = np.einsum("np,np->n", d, d)
    chi2_spike = total - explained[:, 0]
    chi2_star = total - np.max(explained[:, 1:], axis=1)
    dof = d.shape[1] - 2
    spike_fits = chi2_spike <= dof + _HOT_FIT_SIGMAS * math.sqrt(2.0 * dof)
    return spike_fits & (chi2_star - chi2_spike > chi2_limit)


def _psf_fluxes(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float) -> np.ndarray:
    """PSF-fit flux [ADU] of each star at its centroid (module docstring, step 6), every star at once."""
    if x.size == 0:
        return np.zeros(0)
    half = int(math.ceil(_PSF_FIT_SIGMAS * sigma_px)) + 1
    outer = half + _RING_WIDTH_PX
    return _in_chunks(outer, x.size, lambda k: _psf_fluxes_block(sub, x[k], y[k], sigma_px, half, outer))


def _psf_fluxes_block(sub, x, y, sigma_px: float, half: int, outer: int) -> np.ndarray:
    """:func:`_psf_fluxes` of one block of stars."""
    cols, rows, cut, inside = _stamps(sub, x, y, outer)
    offsets = np.abs(np.arange(-outer, outer + 1))
    inner = (offsets[:, None] <= half) & (offsets[None, :] <= half)
    ring = np.where(inside & ~inner, cut, np.nan).reshape(x.size, -1)
    counted = np.any(np.isfinite(ring), axis=1)
    background = np.zeros(x.size)
    background[counted] = np.nanmedian(ring[counted], axis=1)
    p = (
        pixel_integrated_gaussian(rows, y[:, None], sigma_px)[:, :, None]
        * pixel_integrated_gaussian(cols, x[:, None], sigma_px)[:, None, :]
    )
    p = np.where(inside & inner, p, 0.0)
    return np.sum((cut - background[:, None, None]) * p, axis=(1, 2)) / np.sum(p * p, axis=(1, 2))


def _windowed_centroids(sub: np.ndarray, good: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """SEP's windowed centroids (XWIN_IMAGE) with window ``sigma_px``; where the window fails or wanders more than
    :data:`_WINPOS_MAX_SHIFT_PX` from the isophotal barycentre, the barycentre."""
    import sep

    xw, yw, flag = sep.winpos(sub, good["x"], good["y"], np.full(good.size, sigma_px))
    failed = (flag != 0) | (np.hypot(xw - good["x"], yw - good["y"]) > _WINPOS_MAX_SHIFT_PX)
    return np.where(failed, good["x"], xw), np.where(failed, good["y"], yw)


def _unresolved_pairs(
    e: np.ndarray,
    e_sigma: np.ndarray,
    max_ellipticity: float,
    x_px: np.ndarray | None = None,
    y_px: np.ndarray | None = None,
    shape_px: tuple[int, int] | None = None,
) -> np.ndarray:
    """Stars more elongated than the frame's PSF where they are: |e - e_psf(x, y)| beyond ``max_ellipticity`` and
    beyond :data:`_ELLIPTICITY_SIGNIFICANCE` x sqrt(spread^2 + noise^2) (the spread of the stars' ellipticities about
    the model beyond their noise, which also holds what the noise estimate misses, e.g. correlated pixels: a single
    star exceeds it with probability exp(-16 / 2) = 3e-4). ``e_psf`` is :func:`_psf_ellipticity_field`, fitted to
    every star whose ellipticity is known to :data:`_PSF_SHAPE_MAX_SIGMA` (blends are a minority): a real lens's PSF is
    elliptical (coma, astigmatism, an undersampled spot on the pixel grid) by 0.1-0.3 and, in a wide field, changes
    across it (elongated radially towards the edge: on the 27-deg granasat frames e ~ 0.2-0.35 beyond 400 px from the
    centre, against ~0.05 at it). Only what stands out from the PSF of its own part of the field is a blend."""
    reference = np.flatnonzero(e_sigma < _PSF_SHAPE_MAX_SIGMA)
    e_psf, spread = np.zeros_like(e), 0.0
    if reference.size >= _PSF_SHAPE_STARS:
        if x_px is None or y_px is None or shape_px is None:
            x_px, y_px, shape_px = np.zeros(e.shape[0]), np.zeros(e.shape[0]), (1, 1)
        e_psf, spread = _psf_ellipticity_field(e, e_sigma, x_px, y_px, shape_px, reference)
    deviation = np.hypot(*(e - e_psf).T)
    scatter = np.sqrt(spread**2 + e_sigma**2)  # per component: the PSF's own spread and the star's noise
    return (deviation > max_ellipticity) & (deviation > _ELLIPTICITY_SIGNIFICANCE * scatter)


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


def _windowed_ellipticity(
    sub: np.ndarray, rms: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float, gain_e_per_adu: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Ellipticity (Mxx - Myy, 2 Mxy) / (Mxx + Myy) (n, 2) of the Gaussian-weighted (window sigma = the PSF's) second
    moments M of each star around its centroid, and its standard deviation from the pixel noise (linear
    propagation: dM/dI_i = w_i (q_i - M) / sum w I; variance rms^2, plus the star's shot noise I / gain [ADU^2]
    when the gain is known). A round PSF gives 0; two equal stars d apart along x give Mxx - Myy ~ d^2 / 16 over
    Mxx + Myy ~ sigma^2 + d^2 / 16: 0.2 at d = 2 sigma, where no saddle separates them."""
    if x.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    half = int(math.ceil(4 * sigma_px))
    return _in_chunks(
        half, x.size, lambda k: _windowed_ellipticity_block(sub, rms, x[k], y[k], sigma_px, gain_e_per_adu, half)
    )


def _windowed_ellipticity_block(sub, rms, x, y, sigma_px: float, gain_e_per_adu: float | None, half: int):
    """:func:`_windowed_ellipticity` of one block of stars."""
    e = np.zeros((x.size, 2))
    e_sigma = np.full(x.size, np.inf)
    cols, rows, data, inside = _stamps(sub, x, y, half)
    var = np.where(inside, _stamps(rms, x, y, half)[2], 0.0) ** 2
    if gain_e_per_adu:
        var = var + np.maximum(data, 0.0) / gain_e_per_adu
    dx = (cols - x[:, None])[:, None, :]
    dy = (rows - y[:, None])[:, :, None]
    weight = np.where(inside, np.exp(-(dx**2 + dy**2) / (2 * sigma_px**2)), 0.0)
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
    return e, e_sigma


def _frame_psf_sigma_px(sub: np.ndarray, good: np.ndarray) -> float:
    """The frame's PSF sigma [px]: median over its most significant stars of the half-light radius / sqrt(2 ln 2),
    measured within 4 sigma of the previous estimate (three rounds from 1 px)."""
    import sep

    bright = _psf_stars(good)
    if bright.size == 0:
        return _DEFAULT_PSF_SIGMA_PX
    sigma = _DEFAULT_PSF_SIGMA_PX
    for _ in range(_PSF_ITERATIONS):  # the radius bounds how much background noise enters r50
        rmax = np.full(bright.size, max(_PSF_RMAX_SIGMAS * sigma, 2.5))
        r50, flag = sep.flux_radius(sub, bright["x"], bright["y"], rmax, 0.5, subpix=5)
        ok = (flag == 0) & np.isfinite(r50) & (r50 > 0)
        if not np.any(ok):
            return _DEFAULT_PSF_SIGMA_PX
        sigma = float(max(np.median(r50[ok]) / _R50_PER_SIGMA, _MIN_PSF_SIGMA_PX))
    return sigma


def _psf_stars(good: np.ndarray) -> np.ndarray:
    """The frame's most significant isolated detections (by the filtered peak over the threshold: on a noisy frame
    the largest isophotal fluxes are noise blobs, the highest peaks are stars), at most :data:`_PSF_STARS`."""
    isolated = good[good["flag"] == 0]
    return isolated[np.argsort(-(isolated["cpeak"] / isolated["thresh"]))[:_PSF_STARS]]


def _psf_model_sigma_px(sub: np.ndarray, good: np.ndarray, window_sigma_px: float) -> float:
    """The width of the PSF fit's own model, the pixel-integrated Gaussian (:func:`_psf_width_fit_px` on
    :func:`_psf_stars`, started at the window's sigma); the window's sigma when no fit converges. The window's sigma
    (:func:`_frame_psf_sigma_px`, from r50) is that of the star convolved with the pixel and SEP's sub-pixel sampling
    of it: 0.88-0.91 px for a rendered Gaussian of 0.77 px, whose pixel-integrated model then gave bright stars a
    pixel-phase S-curve (docs/realsky.md, "A new camera: what was tried"); it stays the window of the moments (the
    windowed centroid, the blend test), for which a wider window is the stable one."""
    bright = _psf_stars(good)
    fitted = _psf_width_fit_px(sub, bright["x"], bright["y"], window_sigma_px) if bright.size else math.nan
    return float(max(fitted, _MIN_PSF_SIGMA_PX)) if np.isfinite(fitted) else window_sigma_px


#: The PSF width fit (:func:`_psf_width_fit_px`): Gauss-Newton steps, and the largest relative change of the width
#: per step (a star on a faint neighbour's wing must not run off).
_WIDTH_FIT_ITERATIONS = 12
_WIDTH_FIT_MAX_STEP = 0.3


def _psf_width_fit_px(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_start_px: float) -> float:
    """The median over the stars at ``(x, y)`` of the least-squares width of the pixel-integrated Gaussian
    mu = B + N Py(y; s) Px(x; s) (:func:`psf_model`, every parameter free, s too) over the pixels within
    3 ``sigma_start_px`` + 1 of each: d P / d s = -[phi(u) u - phi(l) l] / s with u, l = (c +- 1/2 - x) / s (the
    derivative of Phi((c +- 1/2 - x) / s) in s). NaN when no star's fit converges to a positive width."""
    half = int(math.ceil(_PSF_FIT_SIGMAS * sigma_start_px)) + 1
    cols, rows, data, inside = _stamps(sub, np.asarray(x, float), np.asarray(y, float), half)
    widths = []
    for k in range(cols.shape[0]):
        if not inside[k].all():
            continue
        c, r, d = cols[k], rows[k], data[k].ravel()
        p = np.array([x[k], y[k], 0.0, float(np.median(data[k])), sigma_start_px])
        p[2] = max(float(d.sum() - p[3] * d.size), 1.0)
        for _ in range(_WIDTH_FIT_ITERATIONS):
            s = p[4]
            px, py = pixel_integrated_gaussian(c, p[0], s), pixel_integrated_gaussian(r, p[1], s)
            dpx, dpy = pixel_integrated_gaussian_dsource(c, p[0], s), pixel_integrated_gaussian_dsource(r, p[1], s)
            spx, spy = _pixel_gaussian_dwidth(c, p[0], s), _pixel_gaussian_dwidth(r, p[1], s)
            shape = np.outer(py, px)
            jac = np.stack(
                [
                    p[2] * np.outer(py, dpx).ravel(),
                    p[2] * np.outer(dpy, px).ravel(),
                    shape.ravel(),
                    np.ones(d.size),
                    p[2] * (np.outer(spy, px) + np.outer(py, spx)).ravel(),
                ],
                axis=1,
            )
            step = np.linalg.lstsq(jac, d - p[3] - p[2] * shape.ravel(), rcond=None)[0]
            step *= min(1.0, _WIDTH_FIT_MAX_STEP * s / max(abs(step[4]), 1e-300))
            p = p + step
            if not (p[4] > 0 and p[2] > 0 and abs(p[0] - x[k]) < half and abs(p[1] - y[k]) < half):
                break
        else:
            widths.append(p[4])
    return float(np.median(widths)) if widths else float("nan")


def _pixel_gaussian_dwidth(centres_px: np.ndarray, source_px: float, sigma_px: float) -> np.ndarray:
    """d/ds of :func:`hostlink.sky.render.pixel_integrated_gaussian`: -[phi(u) u - phi(l) l] / s."""
    u = (centres_px + 0.5 - source_px) / sigma_px
    lo = (centres_px - 0.5 - source_px) / sigma_px
    return -(np.exp(-0.5 * u**2) * u - np.exp(-0.5 * lo**2) * lo) / (math.sqrt(2.0 * math.pi) * sigma_px)


# ----------------------------------------------------------------------------------------------------------------
# many images -> a session


def centroid_images(
    paths: Sequence[str | Path],
    options: CentroidOptions = CentroidOptions(),
    times: TimeOptions = TimeOptions(),
) -> CentroidResult:
    """Centroid every image in ``paths`` into one session: a frame per image (in time order; in the given order when
    the time is unknown), ``star_id`` 0, ``mag`` the instrumental magnitude, extra columns ``flux_adu``, ``image``
    (file name) and ``time_source``. Every failure (an unreadable image, no time known for an image, a background
    frame of another size, no star in any image) is a one-line :class:`UserError`."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise UserError("no image given")
    chosen = [k for k, v in _time_choices(times).items() if v]
    if len(chosen) > 1:
        raise UserError(f"give at most one of {', '.join(chosen)}")
    sources = [options.dark, options.median, options.median_of_inputs or None]
    if sum(s is not None for s in sources) > 1:
        raise UserError("give at most one of --dark, --median, --median-of-inputs")
    listed = _read_times_file(Path(times.times_file)) if times.times_file is not None else None
    background = _background_frame(paths, options)

    frames: list[tuple[str, Detections, str]] = []
    blank = 0  # images whose every pixel has one value (a lens cap, no exposure, a failed readout)
    for path in paths:
        image = read_image(path)
        blank += int(image.pixels.size == 0 or float(np.ptp(image.pixels)) == 0.0)
        time_utc, source = image_time(image, times, listed)
        det = centroid_pixels(image.pixels, options, background, image.saturation_adu)
        det.report.path = str(path)
        det.report.time_utc, det.report.time_source = time_utc, source
        frames.append((time_utc, det, source))
    if options.median_of_inputs:
        _check_median_holds_no_stars(background, options, [det.report.kept for _, det, _ in frames])
    if all(det.report.kept == 0 for _, det, _ in frames):
        if blank == len(paths):
            raise UserError(f"no star found: every pixel of each of the {len(paths)} image(s) has one value (blank)")
        raise UserError(f"no star found in any of the {len(paths)} image(s); lower --threshold-sigma")
    if times.time_unknown:
        order = list(range(len(frames)))
    else:
        jd1, jd2 = parse_iso_utc_many([t for t, _, _ in frames])
        order = sorted(range(len(frames)), key=lambda k: (jd1[k] + jd2[k], k))
    return _session([frames[k] for k in order])


def _check_median_holds_no_stars(median: np.ndarray, options: CentroidOptions, kept: list[int]) -> None:
    """Refuse ``--median-of-inputs`` on images that share a pointing: their median then holds their stars, and
    subtracting it removes them. The median of frames at different pointings holds at most a few star-like sources
    (warm pixel clusters, a star that stayed put), fewer than :data:`_MEDIAN_MAX_STARS` and fewer than a frame
    keeps."""
    in_median = centroid_pixels(median, replace(options, max_stars=None, candidate_sigma=None)).report.kept
    per_frame = float(np.mean(kept)) if kept else 0.0
    if in_median >= _MEDIAN_MAX_STARS and in_median >= per_frame:
        raise UserError(
            f"--median-of-inputs: the median of the images holds {in_median} star-like sources (a frame keeps "
            f"{per_frame:.0f}): the images share a pointing and the median would remove their stars; give --dark, "
            "or no background frame"
        )


def _time_choices(times: TimeOptions) -> dict[str, bool]:
    return {
        "--time": times.time_utc is not None,
        "--times": times.times_file is not None,
        "--time-pattern": times.time_pattern is not None,
        "--date": times.date is not None,
        "--time-unknown": bool(times.time_unknown),
    }


def _session(frames: list[tuple[str, Detections, str]]) -> CentroidResult:
    """The session of the frames: per frame its stars (brightest first), then its candidates (most significant first;
    ``snr`` set only on them)."""
    parts = [_frame_rows(det) for _, det, _ in frames]
    counts = [part["x"].size for part in parts]
    n = int(sum(counts))
    frame_no = np.repeat(np.arange(len(frames), dtype=np.int64), counts)

    def cat(name: str) -> np.ndarray:
        return np.concatenate([part[name] for part in parts]) if n else np.zeros(0)

    def repeat(values: list[str]) -> np.ndarray:
        return np.array([v for v, c in zip(values, counts, strict=True) for _ in range(c)], dtype=object)

    flux, snr = cat("flux"), cat("snr")
    extra = {
        "flux_adu": np.array([f"{v:.1f}" for v in flux], dtype=object),
        "sigma_px": np.array([f"{v:.4g}" if np.isfinite(v) else "" for v in cat("sigma_px")], dtype=object),
        "saturated": np.array([str(int(v)) for v in cat("saturated")], dtype=object),
    }
    if any(det.candidates is not None for _, det, _ in frames):
        extra["snr"] = np.array([f"{v:.2f}" if np.isfinite(v) else "" for v in snr], dtype=object)
    extra["image"] = repeat([Path(det.report.path).name for _, det, _ in frames])
    extra["time_source"] = repeat([source for _, _, source in frames])
    session = Session(
        frame=frame_no,
        t_utc=repeat([t for t, _, _ in frames]),
        star_id=np.zeros(n, np.int64),
        x_px=cat("x"),
        y_px=cat("y"),
        mag=cat("mag"),
        extra=extra,
    )
    return CentroidResult(session, [det.report for _, det, _ in frames])


def _frame_rows(det: Detections) -> dict[str, np.ndarray]:
    """One frame's rows of the session: its stars, then its candidates (``snr`` NaN on the stars)."""
    c = det.candidates
    if c is None:
        c = Candidates(*(np.zeros(0) for _ in range(6)))
    return {
        "x": np.concatenate([det.x_px, c.x_px]),
        "y": np.concatenate([det.y_px, c.y_px]),
        "flux": np.concatenate([det.flux_adu, c.flux_adu]),
        "mag": np.concatenate([det.mag, c.mag]),
        "sigma_px": np.concatenate([det.sigma_px, c.sigma_px]),
        "saturated": np.concatenate([det.saturated.astype(np.int64), np.zeros(c.x_px.size, np.int64)]),
        "snr": np.concatenate([np.full(det.x_px.size, np.nan), c.snr]),
    }


def _background_frame(paths: list[Path], options: CentroidOptions) -> np.ndarray | None:
    given = options.dark if options.dark is not None else options.median
    if given is not None:
        return read_image(given).pixels
    if not options.median_of_inputs:
        return None
    if len(paths) < 3:
        raise UserError(f"--median-of-inputs needs at least 3 images taken at different pointings, got {len(paths)}")
    stack = None
    for k, path in enumerate(paths):
        pixels = read_image(path).pixels
        if stack is None:
            stack = np.empty((len(paths), *pixels.shape), dtype=np.float32)
        elif pixels.shape != stack.shape[1:]:
            raise UserError(
                f"{path}: {pixels.shape[1]} x {pixels.shape[0]} px, the first image is "
                f"{stack.shape[2]} x {stack.shape[1]} px: --median-of-inputs needs one size"
            )
        stack[k] = pixels
    return np.median(stack, axis=0).astype(np.float64)


# ----------------------------------------------------------------------------------------------------------------
# time of an image


def image_time(image: RawImage, times: TimeOptions, listed: dict[str, str] | None = None) -> tuple[str, str]:
    """(ISO UTC time or "" when unknown, its source) of one image: the option given, else the file's metadata; no
    time at all is a one-line UserError naming the image."""
    name = image.path.name
    if times.time_unknown:
        return "", "unknown"
    if times.time_utc is not None:
        return _checked_iso(times.time_utc, "--time"), "option"
    if listed is not None:
        if name not in listed:
            raise UserError(f"{image.path}: not listed in the times file {times.times_file}")
        return listed[name], f"times file {Path(str(times.times_file)).name}"
    if times.time_pattern is not None:
        return _time_from_name(image.path, times.time_pattern), f"file name ({times.time_pattern})"
    if times.date is not None:
        return _date_noon(times.date), "date only (time of day unknown: 12:00 UTC)"
    if image.time_utc is not None:
        return image.time_utc, str(image.time_source)
    raise UserError(
        f"{image.path}: no time known (no FITS DATE-OBS / EXIF DateTimeOriginal): give --time, --times FILE, "
        "--time-pattern, --date or --time-unknown"
    )


def _checked_iso(text: str, what: str) -> str:
    try:
        parse_iso_utc_many([text])
    except ValueError as exc:
        raise UserError(f"{what}: {exc}") from None
    return str(text).strip()


def _date_noon(text: str) -> str:
    try:
        day = _dt.date.fromisoformat(str(text).strip())
    except ValueError:
        raise UserError(f"--date: not a date YYYY-MM-DD: {text!r}") from None
    return f"{day.isoformat()}T12:00:00.000Z"


def _time_from_name(path: Path, pattern: str) -> str:
    last: Exception | None = None
    for candidate in (path.name, path.stem):
        try:
            when = _dt.datetime.strptime(candidate, pattern)
            break
        except ValueError as exc:
            last = exc
    else:
        raise UserError(f"{path}: the file name does not match --time-pattern {pattern!r} ({one_line(last)})")
    if when.tzinfo is not None:
        when = when.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def _read_times_file(path: Path) -> dict[str, str]:
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read ({one_line(exc)})") from None
    out: dict[str, str] = {}
    for k, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p.strip() for p in (text.split(",") if "," in text else text.split(None, 1))]
        if len(parts) != 2 or not parts[0] or not parts[1]:
            raise UserError(f"{path}: line {k}: expected 'IMAGE_NAME,ISO_UTC_TIME', got {line.strip()!r}")
        out[Path(parts[0]).name] = _checked_iso(parts[1], f"{path}: line {k}")
    return out


# ----------------------------------------------------------------------------------------------------------------
# the PSF model: the fit and the bound


def psf_model(cols: np.ndarray, rows: np.ndarray, params: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The pixel-integrated Gaussian star on a flat background over the pixels ``rows x cols`` and its Jacobian:
    mu = B + N Py(y) Px(x) for params = (x [px], y [px], N, B) (:func:`hostlink.sky.render.pixel_integrated_gaussian`);
    returns mu (len(rows), len(cols)) and d mu / d params (len(rows), len(cols), 4)."""
    x, y, n, b = (float(v) for v in params)
    px = pixel_integrated_gaussian(cols, x, sigma_px)
    py = pixel_integrated_gaussian(rows, y, sigma_px)
    dpx = pixel_integrated_gaussian_dsource(cols, x, sigma_px)
    dpy = pixel_integrated_gaussian_dsource(rows, y, sigma_px)
    shape = np.outer(py, px)
    jac = np.stack([n * np.outer(py, dpx), n * np.outer(dpy, px), shape, np.ones_like(shape)], axis=-1)
    return b + n * shape, jac


#: Levenberg-Marquardt iterations of the batched PSF fit (a budget: a star not converged within it keeps its windowed
#: centroid; 29 of 2515 on granasat. A budget of 100 converges 18 of them, and on the openstartracker frames raises
#: the calibrated residual from 0.482 to 0.545 px: a fit that wanders that long has not found a star), the damping it
#: starts from (relative to the normal matrix's diagonal, Marquardt 1963) and the relative fall of the cost below
#: which a star has converged.
_FIT_ITERATIONS = 30
_FIT_DAMPING_START = 1e-3
_FIT_COST_RTOL = 1e-10
#: ... or its step has fallen below this fraction of every parameter (relative; rounding of the cost then decides
#: whether a step is taken).
_FIT_STEP_RTOL = 1e-10


#: Pixels of all the stamps processed at once (per array: ~8 MB of float64; a frame of 3000 stars of PSF sigma 1 px
#: in one piece, a defocused one in several): bounds the memory of the per-frame computations.
_STAMP_BUDGET_PX = 1_000_000


def _in_chunks(half_px: int, n: int, block):
    """``block(slice)`` over consecutive slices of the n stars, each of at most :data:`_STAMP_BUDGET_PX` pixels of
    stamps of half-width ``half_px``; the results (an array or a tuple of arrays per slice) concatenated."""
    size = max(1, _STAMP_BUDGET_PX // (2 * half_px + 2) ** 2)
    if n <= size:
        return block(slice(0, n))
    parts = [block(slice(k, min(k + size, n))) for k in range(0, n, size)]
    if isinstance(parts[0], tuple):
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))
    return np.concatenate(parts)


def _stamps(image: np.ndarray, x: np.ndarray, y: np.ndarray, half: int):
    """The (2 half + 1)^2 pixels around each star's nearest pixel: (cols (N, W), rows (N, H) as float pixel
    coordinates, the pixel values (N, H, W) (0 outside the image) and a mask (N, H, W), True inside the image)."""
    h, w = image.shape
    offsets = np.arange(-half, half + 1)
    cols = np.rint(x).astype(np.int64)[:, None] + offsets[None, :]
    rows = np.rint(y).astype(np.int64)[:, None] + offsets[None, :]
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    values = image[np.clip(rows, 0, h - 1)[:, :, None], np.clip(cols, 0, w - 1)[:, None, :]]
    return cols.astype(np.float64), rows.astype(np.float64), np.where(inside, values, 0.0), inside


def psf_model_batch(
    cols: np.ndarray, rows: np.ndarray, params: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`psf_model` for N stars at once: ``cols`` (N, W), ``rows`` (N, H), ``params`` (N, 4) = (x, y, N, B);
    returns mu (N, H, W) and d mu / d params (N, H, W, 4)."""
    x, y, n, b = (params[:, k : k + 1] for k in range(4))
    px = pixel_integrated_gaussian(cols, x, sigma_px)
    py = pixel_integrated_gaussian(rows, y, sigma_px)
    dpx = pixel_integrated_gaussian_dsource(cols, x, sigma_px)
    dpy = pixel_integrated_gaussian_dsource(rows, y, sigma_px)
    shape = py[:, :, None] * px[:, None, :]
    nn = n[:, :, None]
    jac = np.stack(
        [nn * py[:, :, None] * dpx[:, None, :], nn * dpy[:, :, None] * px[:, None, :], shape, np.ones_like(shape)],
        axis=-1,
    )
    return b[:, :, None] + nn * shape, jac


def _levenberg_marquardt_batch(
    cols: np.ndarray, rows: np.ndarray, data: np.ndarray, whiten: np.ndarray, start: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of :func:`psf_model_batch` to every star's pixels at once: minimise
    sum (whiten (mu - data))^2 per star by Levenberg-Marquardt (Marquardt 1963, SIAM J. Appl. Math. 11:431: the step
    solves (J^T J + lambda diag(J^T J)) dp = -J^T r; a step that lowers the cost is taken and lambda / 10, else
    lambda x 10), each star on its own, all in numpy. ``whiten`` (N, H, W) is 1 / the pixel noise (0 for a pixel left
    out). Returns the parameters (N, 4) and whether each converged (its cost falling by less than
    :data:`_FIT_COST_RTOL` relative, or its step below :data:`_FIT_STEP_RTOL` of its parameters) within
    :data:`_FIT_ITERATIONS`."""
    params = start.copy()
    n = params.shape[0]
    r, j, cost = _evaluate_rows(cols, rows, data, whiten, params, np.arange(n), sigma_px)
    damping = np.full(n, _FIT_DAMPING_START)
    done = ~np.isfinite(cost)
    converged = np.zeros(n, dtype=bool)
    eye = np.eye(4)
    for _ in range(_FIT_ITERATIONS):
        active = np.flatnonzero(~done)
        if active.size == 0:
            break
        ja, ra = j[active], r[active]
        jt = np.swapaxes(ja, 1, 2)
        normal = jt @ ja  # J^T J and J^T r per star: batched products (a 3-operand einsum is ~8 times slower)
        gradient = (jt @ ra[..., None])[..., 0]
        diag = np.einsum("nii->ni", normal)
        lhs = normal + damping[active, None, None] * diag[:, :, None] * eye
        step, singular = _solve_each(lhs, gradient)
        step = -step
        done[active[singular]] = True
        trial = params.copy()
        trial[active] += step
        r_new, j_new, cost_new = _evaluate_rows(cols, rows, data, whiten, trial, active, sigma_px)
        better = np.isfinite(cost_new) & (cost_new <= cost[active]) & ~singular
        # the step no longer moves the parameters beyond rounding: at the minimum, whether or not it was taken
        tiny = np.max(np.abs(step) / (np.abs(params[active]) + 1e-12), axis=1) < _FIT_STEP_RTOL
        take = active[better]
        fall = cost[take] - cost_new[better]
        params[take] = trial[take]
        r[take], j[take] = r_new[better], j_new[better]
        cost[take] = cost_new[better]
        damping[take] /= 10.0
        damping[active[~better]] *= 10.0
        settled = np.zeros(active.size, dtype=bool)
        settled[better] = fall <= _FIT_COST_RTOL * np.maximum(cost[take], 1e-300)
        settled |= tiny & ~singular
        converged[active[settled]] = True
        done[active[settled]] = True
        done[active[~better & (damping[active] > 1e12)]] = True
    return params, converged


def _solve_each(lhs: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x with lhs[k] x[k] = rhs[k] for each of the (n, 4, 4) systems, and which are singular (their x 0: a
    degenerate stamp, no fit). numpy refuses the whole batch for one singular system: the batch is then split in
    halves until the singular ones stand alone (each system solved by the same LAPACK call as on its own)."""
    try:
        return np.linalg.solve(lhs, rhs[..., None])[..., 0], np.zeros(lhs.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        if lhs.shape[0] == 1:
            return np.zeros_like(rhs), np.ones(1, dtype=bool)
    half = lhs.shape[0] // 2
    (x1, s1), (x2, s2) = _solve_each(lhs[:half], rhs[:half]), _solve_each(lhs[half:], rhs[half:])
    return np.concatenate([x1, x2]), np.concatenate([s1, s2])


def _evaluate_rows(cols, rows, data, whiten, params, active, sigma_px):
    """Whitened residuals (K, P), Jacobian (K, P, 4) and cost (K,) of the stars ``active`` at ``params[active]``."""
    mu, jac = psf_model_batch(cols[active], rows[active], params[active], sigma_px)
    w = whiten[active]
    k = active.size
    r = ((mu - data[active]) * w).reshape(k, -1)
    j = (jac * w[..., None]).reshape(k, -1, 4)
    return r, j, np.einsum("np,np->n", r, r)


def _psf_fit_centroids(
    sub: np.ndarray, rms: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float, gain_e_per_adu: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximum-likelihood centroids (module docstring, step 4): fit :func:`psf_model` (position, flux, local
    background; the PSF sigma fixed at the frame's) to the pixels within +-(3 sigma + 1) of the windowed centroid by
    weighted least squares (:func:`_levenberg_marquardt_batch`, every star of the frame at once), weights
    1 / sqrt(rms^2 + signal / gain) from the first pass's model (signal term only when the gain is known). A fit
    that does not converge, finds no flux or moves more than :data:`_FIT_MAX_SHIFT_PX` keeps the windowed
    centroid. Returns x, y and whether each star's fit was taken. Pixels outside the image are left out of the fit
    (a star cut by the border is fitted on the pixels it has)."""
    if x.size == 0:
        return x.copy(), y.copy(), np.zeros(0, dtype=bool)
    half = int(math.ceil(_PSF_FIT_SIGMAS * sigma_px)) + 1
    return _in_chunks(half, x.size, lambda k: _psf_fit_block(sub, rms, x[k], y[k], sigma_px, gain_e_per_adu, half))


def _psf_fit_block(sub, rms, x, y, sigma_px: float, gain_e_per_adu: float | None, half: int):
    """:func:`_psf_fit_centroids` of one block of stars."""
    out_x, out_y = x.copy(), y.copy()
    cols, rows, data, inside = _stamps(sub, x, y, half)
    noise_var = np.where(inside, _stamps(rms, x, y, half)[2], 1.0) ** 2
    masked = np.where(inside, data, np.nan).reshape(x.size, -1)
    background = np.nanmedian(masked, axis=1)
    flux = np.maximum(np.nansum(masked - background[:, None], axis=1), 1.0)
    params = np.column_stack([x, y, flux, background])
    whiten = np.where(inside, 1.0 / np.sqrt(noise_var), 0.0)
    params, ok = _levenberg_marquardt_batch(cols, rows, data, whiten, params, sigma_px)
    if gain_e_per_adu and np.any(ok):  # the second pass, weighted by the first's model; where it fails, the first's
        model, _ = psf_model_batch(cols[ok], rows[ok], params[ok], sigma_px)
        variance = noise_var[ok] + np.maximum(model - params[ok, 3, None, None], 0.0) / gain_e_per_adu
        whiten = np.where(inside[ok], 1.0 / np.sqrt(variance), 0.0)
        again, converged = _levenberg_marquardt_batch(cols[ok], rows[ok], data[ok], whiten, params[ok], sigma_px)
        params[np.flatnonzero(ok)[converged]] = again[converged]
    ok &= (
        np.all(np.isfinite(params), axis=1)
        & (params[:, 2] > 0)
        & (np.hypot(params[:, 0] - x, params[:, 1] - y) <= _FIT_MAX_SHIFT_PX)
    )
    out_x[ok], out_y[ok] = params[ok, 0], params[ok, 1]
    return out_x, out_y, ok


# ----------------------------------------------------------------------------------------------------------------
# the bound


def centroid_crb_px(
    x_px: float,
    y_px: float,
    flux_e: float,
    psf_sigma_px: float,
    background_e: float,
    read_noise_e: float,
    gain_e_per_adu: float = 1.0,
    half_width_px: int | None = None,
    star_shot_noise: bool = True,
) -> tuple[float, float]:
    """Cramer-Rao bound (standard deviation per axis [px]) of an unbiased centroid of a star of ``flux_e`` [e-] at
    ``(x_px, y_px)`` imaged with a circular Gaussian PSF of ``psf_sigma_px`` integrated over square pixels
    (:func:`hostlink.sky.render.pixel_integrated_gaussian`, the renderer's model), on a background of
    ``background_e`` [e- per pixel], with shot noise, Gaussian read noise ``read_noise_e`` [e-] and the ADC's
    quantisation (gain^2 / 12 [e-^2]).

    Fisher information over the pixels i of a box of +-``half_width_px`` (default 6 sigma + 2) around the star, for
    the parameters p = (x, y, N, B) (position, flux and background all unknown):
    I = sum_i (d mu_i / dp)(d mu_i / dp)^T / (mu_i + sigma_r^2 + g^2 / 12), mu_i = B + N P_i(x, y): exact for
    Poisson and for Gaussian noise alone, and for both the shifted-Poisson approximation (Huang et al. 2013, Nat.
    Methods 10:653, eq. S5), with the model's derivatives from :func:`psf_model` (tested against finite
    differences). ``star_shot_noise`` False leaves mu_i out of the variance (Gaussian noise alone, the detector's
    gain unknown: ``read_noise_e`` then holds the whole measured pixel noise, background shot noise included).
    Returns sqrt(diag(I^-1)) for x and y."""
    sigma = float(psf_sigma_px)
    half = int(half_width_px if half_width_px is not None else math.ceil(6 * sigma) + 2)
    cols = np.arange(math.floor(x_px) - half, math.floor(x_px) + half + 2, dtype=np.float64)
    rows = np.arange(math.floor(y_px) - half, math.floor(y_px) + half + 2, dtype=np.float64)

    p0 = np.array([x_px, y_px, flux_e, background_e], dtype=np.float64)
    mu, jac = psf_model(cols, rows, p0, sigma)
    jac = jac.reshape(-1, 4).T
    variance = (mu.ravel() if star_shot_noise else 0.0) + read_noise_e**2 + gain_e_per_adu**2 / 12.0
    fisher = (jac / variance) @ jac.T
    cov = np.linalg.inv(fisher)
    return float(math.sqrt(cov[0, 0])), float(math.sqrt(cov[1, 1]))


def centroid_sigma_px(
    x_px: np.ndarray,
    y_px: np.ndarray,
    flux_adu: np.ndarray,
    rms_adu: np.ndarray,
    psf_sigma_px: float,
    gain_e_per_adu: float | None,
) -> np.ndarray:
    """Each star's 1-sigma centroid noise per axis [px] (the ``sigma_px`` column): the larger of the x and y
    Cramer-Rao bounds of :func:`centroid_crb_px` for its PSF-fit ``flux_adu``, the local pixel noise ``rms_adu``
    (the background map at the star: sky shot noise, read noise and quantisation as measured) and the frame's PSF.
    With the gain the star's own shot noise is added (electrons: flux x gain, noise rms x gain); without it the
    bound counts the measured pixel noise alone (the background-limited bound: a bright star's is then too small by
    its shot noise). A star with no positive flux gets NaN."""
    x = np.asarray(x_px, np.float64)
    y = np.asarray(y_px, np.float64)
    out = np.full(x.shape, np.nan)
    gain = float(gain_e_per_adu) if gain_e_per_adu else 1.0
    h, w = rms_adu.shape
    if x.size == 0 or h == 0:
        return out
    finite = np.isfinite(x) & np.isfinite(y)
    noise = np.zeros(x.shape)
    r = np.clip(np.rint(np.where(finite, y, 0.0)).astype(np.int64), 0, h - 1)
    c = np.clip(np.rint(np.where(finite, x, 0.0)).astype(np.int64), 0, w - 1)
    noise[finite] = rms_adu[r[finite], c[finite]]
    ok = finite & (np.asarray(flux_adu) > 0) & (noise > 0)
    if np.any(ok):
        out[ok] = _crb_max_px(
            x[ok],
            y[ok],
            np.asarray(flux_adu, np.float64)[ok] * gain,
            psf_sigma_px,
            noise[ok] * gain,
            bool(gain_e_per_adu),
        )
    return out


def _crb_max_px(
    x_px: np.ndarray, y_px: np.ndarray, flux_e: np.ndarray, psf_sigma_px: float, noise_e: np.ndarray, shot: bool
) -> np.ndarray:
    """max(x, y) of :func:`centroid_crb_px` (no background, Gaussian noise ``noise_e``, no quantisation; the star's
    shot noise when ``shot``) for every star at once: the same Fisher information over the same box per star."""
    sigma = float(psf_sigma_px)
    half = int(math.ceil(6 * sigma) + 2)
    return _in_chunks(
        half, x_px.size, lambda k: _crb_max_block(x_px[k], y_px[k], flux_e[k], sigma, noise_e[k], shot, half)
    )


def _crb_max_block(x_px, y_px, flux_e, sigma: float, noise_e, shot: bool, half: int) -> np.ndarray:
    """:func:`_crb_max_px` of one block of stars."""
    steps = np.arange(-half, half + 2, dtype=np.float64)
    cols = np.floor(x_px)[:, None] + steps[None, :]
    rows = np.floor(y_px)[:, None] + steps[None, :]
    params = np.column_stack([x_px, y_px, flux_e, np.zeros_like(x_px)])
    mu, jac = psf_model_batch(cols, rows, params, sigma)
    variance = (mu if shot else 0.0) + (noise_e**2)[:, None, None]
    jac = jac.reshape(x_px.size, -1, 4)
    weighted = jac / variance.reshape(x_px.size, -1, 1)
    fisher = np.matmul(np.swapaxes(weighted, 1, 2), jac)  # J^T W J per star: a batched product, not a 3-way einsum
    cov = np.linalg.inv(fisher)
    return np.sqrt(np.maximum(cov[:, 0, 0], cov[:, 1, 1]))
