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
   of 8-16 sigma into bright neighbours 8-18 px away: :data:`_SEP_CLEAN`); on a frame whose PSF, measured on a first
   extraction, is undersampled (sigma below ~0.575 px, a 2 x 2 binned frame's), also a footprint of 1 filtered pixel
   whose peak reaches 1.2 x the threshold and which fits a star better than a hot pixel
   (:func:`hostlink.images.centroid.screen._footprint_px`); on a frame whose PSF sigma is under 0.85 px, detected at
   3.5 sigma or more, the faint detections decided by a bank of matched filters of the PSF's width at half-pixel
   phases, its threshold raised to hold the false-alarm rate (:mod:`hostlink.images.centroid.phases`);
3. reject, each counted: a *hot pixel* (a single bright pixel explains the detection better than a star of the
   frame's measured PSF, by a likelihood-ratio test, :func:`_hot_pixels`: a sharp star passes, however little of its
   flux its neighbours hold; at the border too; and one clipped pixel whose neighbours hold less than the sharpest
   star would, :func:`hostlink.images.centroid.screen._clipped_spikes`), *without flux* (no positive PSF flux:
   noise); keep, flagged and counted, a *blend* (SEP's ``OBJ_MERGED`` flag: deblended from a neighbour within
   :data:`_BLEND_CLEAR_SIGMAS` PSF sigmas, :func:`_neighbour_bias_px`; or Gaussian-windowed second moments more
   elongated than the PSF of the star's own part of the field, :func:`_unresolved_pairs`,
   :func:`_psf_ellipticity_field`, :func:`_shape_bias_px`: two stars closer than the deblender can split) with the
   bound on its centroid's bias in its ``sigma_px`` (an elongated one's also in ``blend_px``, which identification
   takes out where its blend reference models the companion: :mod:`hostlink.images.blends`), rejected as
   *blended* only when that bound exceeds :data:`_BLEND_MAX_BIAS_PX`; a star *cut by the border* (``OBJ_TRUNC``) is
   centroided on the part of its image point-symmetric about it (:func:`_border_windows`) and fitted on the pixels
   it has, rejected at the *edge* only when that window fails; a *saturated* star (a pixel of the footprint at the
   image's clip level) is kept, flagged and counted (``keep_saturated``, the default: the brightest stars are the
   anchors of identification), or rejected and counted;
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

The package's modules: ``options`` (what is asked and reported), ``frame`` (one image, stage by stage), ``screen``
(extraction, hot pixels, the screening), ``phases`` (the half-pixel-phase filter bank of sharp frames), ``windows``
(windowed centroids, the PSF's width), ``shapes`` (blends and their bias), ``psf`` (the PSF model, its fit, flux and
bound), ``candidates`` (the faint candidates), ``stamps`` (pixels around stars, in blocks), ``session`` (many images ->
a session), ``times`` (the time of each image).
"""

from __future__ import annotations

from hostlink.images.centroid.candidates import _candidates as _candidates
from hostlink.images.centroid.candidates import _snr as _snr
from hostlink.images.centroid.frame import centroid_pixels
from hostlink.images.centroid.options import (
    CENTROID_METHODS,
    DEFAULT_CANDIDATE_SIGMA,
    SATURATED_SIGMA_PX,
    Candidates,
    CentroidOptions,
    CentroidResult,
    Detections,
    FrameReport,
    TimeOptions,
)
from hostlink.images.centroid.psf import _psf_fit_centroids as _psf_fit_centroids
from hostlink.images.centroid.psf import _solve_each as _solve_each
from hostlink.images.centroid.psf import centroid_crb_px, centroid_sigma_px, psf_model, psf_model_batch
from hostlink.images.centroid.session import centroid_images
from hostlink.images.centroid.times import image_time
from hostlink.images.centroid.windows import _window_iterated as _window_iterated

#: Pixels of all the stamps processed at once (per array: ~8 MB of float64; a frame of 3000 stars of PSF sigma 1 px
#: in one piece, a defocused one in several): bounds the memory of the per-frame computations
#: (:func:`hostlink.images.centroid.stamps._in_chunks` reads it here).
_STAMP_BUDGET_PX = 1_000_000

__all__ = [
    "CENTROID_METHODS",
    "DEFAULT_CANDIDATE_SIGMA",
    "SATURATED_SIGMA_PX",
    "Candidates",
    "CentroidOptions",
    "CentroidResult",
    "Detections",
    "FrameReport",
    "TimeOptions",
    "centroid_crb_px",
    "centroid_images",
    "centroid_pixels",
    "centroid_sigma_px",
    "image_time",
    "psf_model",
    "psf_model_batch",
]
