"""The faint candidates below the detection threshold (:mod:`hostlink.images.centroid`, step 7)."""

from __future__ import annotations

import numpy as np

from hostlink.images.centroid.options import Candidates, CentroidOptions, Detections
from hostlink.images.centroid.psf import (
    _PSF_FIT_SIGMAS,
    _noise_stated,
    _psf_fit_half_px,
    _psf_fluxes,
    centroid_sigma_px,
)
from hostlink.images.centroid.screen import _HOT_BOX_HALF_PX
from hostlink.images.centroid.stamps import _in_chunks
from hostlink.images.centroid.windows import _window_half_px, _window_iterated
from hostlink.sky.render import pixel_integrated_gaussian

#: A candidate's peak lies at least this far [px] from every kept star, in PSF sigmas plus 1 px (the fit's stamp,
#: :data:`_PSF_FIT_SIGMAS`: nearer, a star's wing and the candidate share pixels).
_CANDIDATE_CLEAR_SIGMAS = _PSF_FIT_SIGMAS


def _candidates(sub, rms, significance, segmap, kept: Detections, sigma: float, options: CentroidOptions) -> Candidates:
    """Package docstring, step 7: faint candidates, the local maxima of the detection's ``significance`` (its
    filtered image over its noise, :func:`hostlink.images.centroid.screen._extract`) outside every detection's
    footprint (below the threshold, or lost by the extraction) and clear of the kept stars, centroided by the window
    of the PSF's width (:func:`_window_iterated`: where the background's noise dominates, as it does for every faint
    star, the matched filter, the maximum-likelihood centroid) and kept when their PSF-fit flux F is at
    least ``candidate_sigma`` x its noise: snr = F sqrt(sum P^2) / rms (:func:`_snr`). Most are noise, and they are
    not tested for hot pixels: :mod:`hostlink.images.guided` names one only where the calibrated camera predicts a
    catalogue star as bright, and states the chance of that for noise, counting every candidate (hot pixels too)."""
    rows, cols = _local_maxima(significance, options.candidate_sigma, segmap)
    x0, y0 = cols.astype(np.float64), rows.astype(np.float64)
    clear = _CANDIDATE_CLEAR_SIGMAS * sigma + 1.0
    if kept.x_px.size and x0.size:
        from scipy.spatial import cKDTree

        near, _ = cKDTree(np.column_stack([kept.x_px, kept.y_px])).query(np.column_stack([x0, y0]))
        x0, y0, rows, cols = x0[near > clear], y0[near > clear], rows[near > clear], cols[near > clear]
    x, y = _in_chunks(_window_half_px(sigma), x0.size, lambda k: _window_iterated(sub, x0[k], y0[k], sigma))
    flux = _psf_fluxes(sub, x, y, sigma)
    snr = _snr(sub, rms, x, y, sigma, flux)
    keep = np.flatnonzero(snr >= options.candidate_sigma)
    keep = keep[np.argsort(-snr[keep], kind="stable")]
    x, y, flux, snr = x[keep], y[keep], flux[keep], snr[keep]
    sigma_px = centroid_sigma_px(x, y, flux, rms, sigma, options.gain_e_per_adu)
    stated = _noise_stated(sigma_px)  # a row without a centroid noise is not written
    x, y, flux, sigma_px, snr = x[stated], y[stated], flux[stated], sigma_px[stated], snr[stated]
    return Candidates(x, y, flux, -2.5 * np.log10(flux), sigma_px, snr)


def _local_maxima(significance: np.ndarray, limit: float, segmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels of ``significance`` at least ``limit``, outside every footprint (``segmap`` 0),
    at least :data:`_HOT_BOX_HALF_PX` from the border, and not below any of their 8 neighbours."""
    h, w = significance.shape
    m = _HOT_BOX_HALF_PX
    # by flat indices (faster than by rows and columns), the footprints looked up at the pixels at the limit alone
    rows, cols = np.divmod(np.flatnonzero(significance[m : h - m, m : w - m] >= limit), w - 2 * m)
    at = (rows + m) * w + (cols + m)
    at = at[segmap.ravel()[at] == 0]
    flat = significance.ravel()
    value = flat[at]
    peak = np.ones(at.size, dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                peak &= value >= flat[at + dr * w + dc]
    return np.divmod(at[peak], w)


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
    half = _psf_fit_half_px(sigma_px)
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    cols = np.rint(x)[:, None] + offsets[None, :]
    rows = np.rint(y)[:, None] + offsets[None, :]
    px = pixel_integrated_gaussian(cols, x[:, None], sigma_px)
    py = pixel_integrated_gaussian(rows, y[:, None], sigma_px)
    return np.sum(px * px, axis=1) * np.sum(py * py, axis=1)
