"""Windowed centroids (Source Extractor's XWIN_IMAGE): SEP's, the batched one of the faint candidates, the one over
the point-symmetric part of a star the border cuts; and the frame's PSF width, the window's (from r50) and the PSF
model's (:mod:`hostlink.images.centroid`, step 4)."""

from __future__ import annotations

import math

import numpy as np

from hostlink.images.centroid.psf import _psf_fit_half_px
from hostlink.images.centroid.stamps import _stamps
from hostlink.sky.render import (
    pixel_integrated_gaussian,
    pixel_integrated_gaussian_dsource,
    pixel_integrated_gaussian_dwidth,
)

#: r50 / sigma of a circular Gaussian: sqrt(2 ln 2).
_R50_PER_SIGMA = math.sqrt(2.0 * math.log(2.0))


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


#: ``sep.winpos`` weighs the pixels its 4-sigma circle cuts by their exact overlap with it (0), not by 11 x 11
#: sub-pixels (Source Extractor's default): the same centroids within 8e-5 px for 99 % of granasat's detections
#: (0.015 px at most, a faint star), in 40 % of the time (docs/realsky.md, "Time").
_WINPOS_SUBPIX = 0


#: A windowed centroid that moves farther than this from the isophotal one [px] has failed (a neighbour pulled it).
_WINPOS_MAX_SHIFT_PX = 2.0


#: The candidates' window: iterations, and the stamp's half-width in window sigmas (+1 px).
_WINDOW_ITERATIONS = 8


_WINDOW_HALF_SIGMAS = 4


def _window_half_px(sigma_px: float) -> int:
    """The half-width [px] of the windowed centroid's stamps for a window of ``sigma_px``: 4 sigma + 1 px, rounded
    up (:data:`_WINDOW_HALF_SIGMAS`)."""
    return int(math.ceil(_WINDOW_HALF_SIGMAS * sigma_px)) + 1


def _window_iterated(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Source Extractor's windowed centroid (XWIN_IMAGE, Bertin's SExtractor manual, "windowed positional
    parameters") of every star at once: x <- x + 2 sum w I (x_i - x) / sum w I with the Gaussian window
    w = exp(-r^2 / (2 sigma^2)) over +-(4 sigma + 1) px, :data:`_WINDOW_ITERATIONS` times (as ``sep.winpos`` does for
    one star at a time); a star whose step leaves the stamp, or whose windowed flux is not positive, keeps its
    start."""
    half = _window_half_px(sigma_px)
    cols, rows, data, _ = _stamps(sub, x, y, half)
    cx, cy = x.copy(), y.copy()
    ok = np.ones(x.size, dtype=bool)
    for _ in range(_WINDOW_ITERATIONS):
        wx = np.exp(-0.5 * ((cols - cx[:, None]) / sigma_px) ** 2)
        wy = np.exp(-0.5 * ((rows - cy[:, None]) / sigma_px) ** 2)
        cx, cy, ok = _window_step(cols, rows, data, wx, wy, cx, cy, ok, x, y)
    return np.where(ok, cx, x), np.where(ok, cy, y)


def _window_step(cols, rows, data, wx, wy, cx, cy, ok, x, y):
    """One step of the windowed centroid, x <- x + 2 sum w I (x_i - x) / sum w I (:func:`_window_iterated`), with the
    separable window ``wx`` (N, W) x ``wy`` (N, H) at (``cx``, ``cy``): the new centroids and ``ok`` less the stars
    whose windowed flux is not positive or whose centroid moved more than :data:`_WINPOS_MAX_SHIFT_PX` from (``x``,
    ``y``) (a failed star's centroid is left where it was)."""
    wi = wy[:, :, None] * wx[:, None, :] * data
    total = np.sum(wi, axis=(1, 2))
    ok = ok & (total > 0)
    safe = np.where(ok, total, 1.0)
    cx_new = cx + np.where(ok, 2.0 * np.sum(wi * (cols - cx[:, None])[:, None, :], axis=(1, 2)) / safe, 0.0)
    cy_new = cy + np.where(ok, 2.0 * np.sum(wi * (rows - cy[:, None])[:, :, None], axis=(1, 2)) / safe, 0.0)
    ok &= (np.abs(cx_new - x) <= _WINPOS_MAX_SHIFT_PX) & (np.abs(cy_new - y) <= _WINPOS_MAX_SHIFT_PX)
    return cx_new, cy_new, ok


def _border_windows(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float):
    """Windowed centroids (:func:`_window_iterated`'s iteration, from ``x``, ``y``) of stars the border cuts, each
    over a region point-symmetric about its current centroid: along each axis the pixels within D of it, D its
    distance to the image's edge (the outer pixel's edge), a pixel the region's boundary cuts weighted by its share
    inside. The first moment of a point-symmetric star over a region point-symmetric about its centre vanishes, so
    the missing side biases nothing (over the pixels there are, the window pulls the centroid inwards by up to a PSF
    sigma; a saturated core's is the only centroid there is). Returns x, y and the share of the window's weight the
    region holds at the end (0 where the centroid failed: no positive windowed flux, or a step leaving the
    stamp)."""
    half = _window_half_px(sigma_px)
    cols, rows, data, inside = _stamps(sub, x, y, half)
    h, w = sub.shape
    cx, cy = x.copy(), y.copy()
    ok = np.ones(x.size, dtype=bool)
    for _ in range(_WINDOW_ITERATIONS):
        wx, wy, _ = _symmetric_window(cols, rows, cx, cy, sigma_px, w, h)
        cx, cy, ok = _window_step(cols, rows, data, wx, wy, cx, cy, ok, x, y)
    *_, share = _symmetric_window(cols, rows, cx, cy, sigma_px, w, h)
    return np.where(ok, cx, x), np.where(ok, cy, y), np.where(ok, share, 0.0)


def _symmetric_window(cols, rows, cx, cy, sigma_px: float, width: int, height: int):
    """The window of :func:`_border_windows` along x (N, W) and y (N, H) at (cx, cy): the Gaussian of ``sigma_px``
    times each pixel's share of [c - D, c + D], D the distance from c to the nearer edge of the image (at -0.5 and
    size - 0.5); and the share of the full window's weight it keeps (N,)."""

    def axis(at: np.ndarray, centre: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        reach = np.maximum(np.minimum(centre + 0.5, size - 0.5 - centre), 0.0)[:, None]
        inside = np.clip(
            np.minimum(at + 0.5, centre[:, None] + reach) - np.maximum(at - 0.5, centre[:, None] - reach), 0.0, 1.0
        )
        gauss = np.exp(-0.5 * ((at - centre[:, None]) / sigma_px) ** 2)
        return gauss * inside, gauss

    wx, gx = axis(cols, cx, width)
    wy, gy = axis(rows, cy, height)
    share = np.sum(wx, axis=1) * np.sum(wy, axis=1) / (np.sum(gx, axis=1) * np.sum(gy, axis=1))
    return wx, wy, share


def _windowed_centroids(sub: np.ndarray, good: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """SEP's windowed centroids (XWIN_IMAGE) with window ``sigma_px``; where the window fails or wanders more than
    :data:`_WINPOS_MAX_SHIFT_PX` from the isophotal barycentre, the barycentre."""
    import sep

    xw, yw, flag = sep.winpos(sub, good["x"], good["y"], np.full(good.size, sigma_px), subpix=_WINPOS_SUBPIX)
    failed = (flag != 0) | (np.hypot(xw - good["x"], yw - good["y"]) > _WINPOS_MAX_SHIFT_PX)
    return np.where(failed, good["x"], xw), np.where(failed, good["y"], yw)


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
    """The width of the PSF fit's own model, the pixel-integrated Gaussian
    (:func:`_psf_width_fit_px` on :func:`_psf_stars`, started at the window's sigma); the
    window's sigma when no fit converges. The window's sigma (:func:`_frame_psf_sigma_px`, from r50) is that of the
    star convolved with the pixel and SEP's sub-pixel sampling of it: 0.88-0.91 px for a rendered Gaussian of
    0.77 px, whose pixel-integrated model then gave bright stars a pixel-phase S-curve (docs/realsky.md, "A new
    camera: what was tried"); it stays the window of the moments (the windowed centroid, the blend test), for which a
    wider window is the stable one."""
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
    half = _psf_fit_half_px(sigma_start_px)
    x, y = np.asarray(x, float), np.asarray(y, float)
    cols, rows, data, inside = _stamps(sub, x, y, half)
    # the fit is a function of these alone; a frame asks it twice of the same stars (its first extraction's most
    # significant ones, then the screened frame's), the second time answered from the first
    key = (x.tobytes(), y.tobytes(), float(sigma_start_px), data.tobytes(), inside.tobytes())
    last = _LAST_WIDTH_FIT[-1] if _LAST_WIDTH_FIT else None  # one (key, width) tuple, replaced whole: thread-safe
    if last is not None and last[0] == key:
        return last[1]
    width = _width_fit_median_px(x, y, cols, rows, data, inside, sigma_start_px, half)
    _LAST_WIDTH_FIT[:] = [(key, width)]
    return width


#: The last :func:`_psf_width_fit_px` as one (inputs, width) tuple: its inputs (positions, start, the stamps' pixels)
#: decide the width, so a hit is the same answer whichever frame or thread asked.
_LAST_WIDTH_FIT: list[tuple[tuple, float]] = []


def _width_fit_median_px(x, y, cols, rows, data, inside, sigma_start_px: float, half: int) -> float:
    """:func:`_psf_width_fit_px` on the stamps of half-width ``half`` around the stars."""
    whole = np.flatnonzero(inside.reshape(x.size, -1).all(axis=1))
    p = np.zeros((whole.size, 5))
    for i, k in enumerate(whole):
        d = data[k].ravel()
        p[i] = [x[k], y[k], 0.0, float(np.median(data[k])), sigma_start_px]
        p[i, 2] = max(float(d.sum() - p[i, 3] * d.size), 1.0)
    running = np.ones(whole.size, dtype=bool)  # no step has left the bounds yet
    for _ in range(_WIDTH_FIT_ITERATIONS):
        if not running.any():
            break
        at = np.flatnonzero(running)
        jacobians, residuals = _width_fit_rows(cols[whole[at]], rows[whole[at]], data[whole[at]], p[at])
        for i, jac, residual in zip(at, jacobians, residuals, strict=True):
            k, width = whole[i], p[i, 4]
            step = np.linalg.lstsq(jac, residual, rcond=None)[0]
            step *= min(1.0, _WIDTH_FIT_MAX_STEP * width / max(abs(step[4]), 1e-300))
            p[i] = p[i] + step
            if not (p[i, 4] > 0 and p[i, 2] > 0 and abs(p[i, 0] - x[k]) < half and abs(p[i, 1] - y[k]) < half):
                running[i] = False
    widths = p[running, 4]
    return float(np.median(widths)) if widths.size else float("nan")


def _width_fit_rows(cols, rows, data, p):
    """The Jacobian (K, P, 5) of :func:`_psf_width_fit_px`'s model at ``p`` (K, 5) = (x, y, N, B, s) of K stars,
    d mu / d (x, y, N, B) as :func:`psf_model` makes it (every star with its own width) and d mu / d s, and the
    residuals its step fits, (K, P): every star's pixels at once (one call per function for all, not per star)."""
    k = p.shape[0]
    x, y, n, b, s = (p[:, i : i + 1] for i in range(5))
    px, py = pixel_integrated_gaussian(cols, x, s), pixel_integrated_gaussian(rows, y, s)
    dpx, dpy = pixel_integrated_gaussian_dsource(cols, x, s), pixel_integrated_gaussian_dsource(rows, y, s)
    spx, spy = pixel_integrated_gaussian_dwidth(cols, x, s), pixel_integrated_gaussian_dwidth(rows, y, s)
    nn = n[:, :, None]
    shape = py[:, :, None] * px[:, None, :]
    jac = np.empty((*shape.shape, 5))
    jac[..., 0] = nn * (py[:, :, None] * dpx[:, None, :])  # psf_model's n * outer(py, dpx)
    jac[..., 1] = nn * (dpy[:, :, None] * px[:, None, :])
    jac[..., 2] = shape
    jac[..., 3] = 1.0
    jac[..., 4] = nn * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :])
    jac = jac.reshape(k, -1, 5)
    return jac, data.reshape(k, -1) - b - n * jac[:, :, 2]
