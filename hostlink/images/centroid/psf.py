"""The pixel-integrated Gaussian PSF: its model, the batched maximum-likelihood fit of every star of a frame, the
model's own width, the PSF flux, and the Cramer-Rao bound of a centroid (:mod:`hostlink.images.centroid`, steps
4-6)."""

from __future__ import annotations

import math

import numpy as np

from hostlink.images.centroid.stamps import _in_chunks, _stamps
from hostlink.images.order_statistics import row_medians
from hostlink.sky.render import pixel_integrated_gaussian, pixel_integrated_gaussian_dsource

#: The PSF flux is fitted over +-this many PSF sigmas (+1 px) around the centroid; the local background is the median
#: of the ring from there out to 3 px farther.
_PSF_FIT_SIGMAS = 3.0


_RING_WIDTH_PX = 3


def _psf_fit_half_px(sigma_px: float) -> int:
    """The half-width [px] of the PSF fit's stamp (and the flux's): 3 PSF sigmas (:data:`_PSF_FIT_SIGMAS`) + 1 px,
    rounded up."""
    return int(math.ceil(_PSF_FIT_SIGMAS * sigma_px)) + 1


#: The Cramer-Rao bound's box: +-(this many PSF sigmas + 2 px), rounded up (a box 15 px wider moves the bound by
#: < 3e-5 relative for PSF sigmas 0.45-2.5 px: the pixels beyond hold no star light, only the background's).
_CRB_BOX_SIGMAS = 6


def _crb_half_px(sigma_px: float) -> int:
    """The half-width [px] of :func:`centroid_crb_px`'s default box: :data:`_CRB_BOX_SIGMAS` sigmas + 2 px, rounded
    up."""
    return int(math.ceil(_CRB_BOX_SIGMAS * sigma_px) + 2)


#: A PSF fit that moves the centroid farther than this from the windowed one [px] has failed (a neighbour, noise).
_FIT_MAX_SHIFT_PX = 1.0


def _noise_stated(sigma_px: np.ndarray) -> np.ndarray:
    """(N,) bool: ``sigma_px`` is a finite positive number (every row written carries one: calibrate weighs by it)."""
    return np.isfinite(sigma_px) & (sigma_px > 0)


def _psf_fluxes(sub: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float) -> np.ndarray:
    """PSF-fit flux [ADU] of each star at its centroid (package docstring, step 6), every star at once."""
    if x.size == 0:
        return np.zeros(0)
    half = _psf_fit_half_px(sigma_px)
    outer = half + _RING_WIDTH_PX
    return _in_chunks(outer, x.size, lambda k: _psf_fluxes_block(sub, x[k], y[k], sigma_px, half, outer))


def _psf_fluxes_block(sub, x, y, sigma_px: float, half: int, outer: int) -> np.ndarray:
    """:func:`_psf_fluxes` of one block of stars."""
    cols, rows, cut, inside = _stamps(sub, x, y, outer)
    offsets = np.abs(np.arange(-outer, outer + 1))
    inner = (offsets[:, None] <= half) & (offsets[None, :] <= half)
    ring = ~inner.ravel()
    background = row_medians(cut.reshape(x.size, -1)[:, ring], inside.reshape(x.size, -1)[:, ring])
    background[~np.isfinite(background)] = 0.0
    p = np.where(inside & inner, _psf_shape_batch(cols, rows, x, y, sigma_px), 0.0)
    return np.sum((cut - background[:, None, None]) * p, axis=(1, 2)) / np.sum(p * p, axis=(1, 2))


def _psf_shape_batch(cols: np.ndarray, rows: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float) -> np.ndarray:
    """(N, H, W): each star's pixel-integrated Gaussian of unit flux, Py(y) Px(x) (:func:`psf_model_batch` with
    N = 1, B = 0, without its Jacobian), over its pixels ``rows`` (N, H) x ``cols`` (N, W), the star at ``x``, ``y``
    (N,) [px]."""
    return (
        pixel_integrated_gaussian(rows, y[:, None], sigma_px)[:, :, None]
        * pixel_integrated_gaussian(cols, x[:, None], sigma_px)[:, None, :]
    )


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


def psf_model_batch(
    cols: np.ndarray, rows: np.ndarray, params: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`psf_model` for N stars at once: ``cols`` (N, W), ``rows`` (N, H), ``params`` (N, 4) = (x, y, N, B);
    returns mu (N, H, W) and d mu / d params (N, H, W, 4)."""
    mu, (dx, dy, shape) = _model_columns(cols, rows, params, sigma_px)
    return mu, np.stack([dx, dy, shape, np.ones_like(shape)], axis=-1)


def _model_columns(
    cols: np.ndarray, rows: np.ndarray, params: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`psf_model_batch`'s mu and the first three columns of its Jacobian, d mu / d (x, y, N), each (N, H, W)
    (the fourth, d mu / d B, is 1)."""
    x, y, n, b = (params[:, k : k + 1] for k in range(4))
    px = pixel_integrated_gaussian(cols, x, sigma_px)
    py = pixel_integrated_gaussian(rows, y, sigma_px)
    dpx = pixel_integrated_gaussian_dsource(cols, x, sigma_px)
    dpy = pixel_integrated_gaussian_dsource(rows, y, sigma_px)
    shape = py[:, :, None] * px[:, None, :]
    nn = n[:, :, None]
    columns = (nn * py[:, :, None] * dpx[:, None, :], nn * dpy[:, :, None] * px[:, None, :], shape)
    return b[:, :, None] + nn * shape, columns


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
        every = active.size == n  # every star still active (the first iterations): no copy of their rows
        ja, ra = (j, r) if every else (j[active], r[active])
        jt = np.swapaxes(ja, 1, 2)
        normal = jt @ ja  # J^T J and J^T r per star: batched products (a 3-operand einsum is slower: docs/realsky.md)
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
        if every and take.size == n:  # every star's step taken: the new rows are the rows
            r, j = r_new, j_new
        else:
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
    degenerate stamp, no fit). The whole batch is solved in one call (each system by the same LAPACK call as on its
    own); numpy refuses it for one singular system, and then the singular ones are found, an exact zero pivot of the
    LU factorisation (``np.linalg.slogdet``'s sign 0: LAPACK's getrf, with which ``np.linalg.solve``'s gesv starts
    and on which it fails), and the others solved in one call. Should solve still refuse them, the batch is split in
    halves until the singular ones stand alone (alone, that took a split per level for every singular system in the
    batch)."""
    try:  # the common batch, none singular: no determinants first
        return np.linalg.solve(lhs, rhs[..., None])[..., 0], np.zeros(lhs.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    singular = np.linalg.slogdet(lhs)[0] == 0
    if singular.any():
        out = np.zeros_like(rhs)
        if not singular.all():
            out[~singular], again = _solve_halving(lhs[~singular], rhs[~singular])
            singular[np.flatnonzero(~singular)[again]] = True
        return out, singular
    return _solve_halving(lhs, rhs)


def _solve_halving(lhs: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_solve_each` by splitting the batch in halves until the singular systems stand alone."""
    try:
        return np.linalg.solve(lhs, rhs[..., None])[..., 0], np.zeros(lhs.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        if lhs.shape[0] == 1:
            return np.zeros_like(rhs), np.ones(1, dtype=bool)
    half = lhs.shape[0] // 2
    (x1, s1), (x2, s2) = _solve_halving(lhs[:half], rhs[:half]), _solve_halving(lhs[half:], rhs[half:])
    return np.concatenate([x1, x2]), np.concatenate([s1, s2])


def _evaluate_rows(cols, rows, data, whiten, params, active, sigma_px):
    """Whitened residuals (K, P), Jacobian (K, P, 4) and cost (K,) of the stars ``active`` at ``params[active]``: the
    columns of :func:`psf_model_batch`'s Jacobian each times the whitening, written in place (no stacked Jacobian
    and no product of it: docs/realsky.md, "Time"; d mu / d B = 1 whitened is the whitening)."""
    k = active.size
    if k != data.shape[0]:  # some stars only (holding every star, ``active`` is 0 .. n - 1: no copies needed)
        cols, rows, params, data, whiten = (v[active] for v in (cols, rows, params, data, whiten))
    mu, columns = _model_columns(cols, rows, params, sigma_px)
    w = whiten
    r = ((mu - data) * w).reshape(k, -1)
    j = np.empty((*w.shape, 4))
    for c, column in enumerate(columns):
        np.multiply(column, w, out=j[..., c])
    j[..., 3] = w
    j = j.reshape(k, -1, 4)
    return r, j, np.einsum("np,np->n", r, r)


def _psf_fit_centroids(
    sub: np.ndarray, rms: np.ndarray, x: np.ndarray, y: np.ndarray, sigma_px: float, gain_e_per_adu: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximum-likelihood centroids (package docstring, step 4): fit :func:`psf_model` (position, flux, local
    background; the PSF sigma fixed at the frame's) to the pixels within +-(3 sigma + 1) of the windowed centroid by
    weighted least squares (:func:`_levenberg_marquardt_batch`, every star of the frame at once), weights
    1 / sqrt(rms^2 + signal / gain) from the first pass's model (signal term only when the gain is known). A fit
    that does not converge, finds no flux or moves more than :data:`_FIT_MAX_SHIFT_PX` keeps the windowed
    centroid. Returns x, y and whether each star's fit was taken. Pixels outside the image are left out of the fit
    (a star cut by the border is fitted on the pixels it has)."""
    if x.size == 0:
        return x.copy(), y.copy(), np.zeros(0, dtype=bool)
    half = _psf_fit_half_px(sigma_px)
    return _in_chunks(half, x.size, lambda k: _psf_fit_block(sub, rms, x[k], y[k], sigma_px, gain_e_per_adu, half))


def _psf_fit_block(sub, rms, x, y, sigma_px: float, gain_e_per_adu: float | None, half: int):
    """:func:`_psf_fit_centroids` of one block of stars."""
    out_x, out_y = x.copy(), y.copy()
    cols, rows, data, inside = _stamps(sub, x, y, half)
    noise_var = np.where(inside, _stamps(rms, x, y, half)[2], 1.0) ** 2
    background = row_medians(data.reshape(x.size, -1), inside.reshape(x.size, -1))
    masked = np.where(inside, data, np.nan).reshape(x.size, -1)
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
    half = int(half_width_px if half_width_px is not None else _crb_half_px(sigma))
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
            (h, w),
        )
    return out


def _crb_max_px(
    x_px: np.ndarray,
    y_px: np.ndarray,
    flux_e: np.ndarray,
    psf_sigma_px: float,
    noise_e: np.ndarray,
    shot: bool,
    shape_px: tuple[int, int] | None = None,
) -> np.ndarray:
    """max(x, y) of :func:`centroid_crb_px` (no background, Gaussian noise ``noise_e``, no quantisation; the star's
    shot noise when ``shot``) for every star at once: the same Fisher information over the same box per star, over
    the pixels of the image (``shape_px`` (rows, columns); None: unbounded) alone: a star the border cuts carries
    the information of the pixels it has."""
    sigma = float(psf_sigma_px)
    half = _crb_half_px(sigma)
    block = _crb_max_block if shot else _crb_max_separable  # no shot noise: the sums separate into row and column sums
    return _in_chunks(
        half,
        x_px.size,
        lambda k: block(x_px[k], y_px[k], flux_e[k], sigma, noise_e[k], shot, half, shape_px),
    )


def _crb_max_separable(x_px, y_px, flux_e, sigma: float, noise_e, shot: bool, half: int, shape_px=None) -> np.ndarray:
    """:func:`_crb_max_block` when every pixel's variance is the star's ``noise_e``^2 (no shot noise): over the
    box's pixels inside the image (a rectangle), each Fisher entry sum_ij J_i J_j of the separable model
    mu = B + N Py(y) Px(x) is a product of a sum over the rows and one over the columns, e.g.
    sum (N Py dPx)^2 = N^2 (sum Py^2)(sum dPx^2): the same information in O(W) per star instead of O(W^2) (equal to
    the pixel-by-pixel sums to rounding, tested). ``shot`` must be False (the signature of :func:`_crb_max_block`)."""
    assert not shot, "the star's shot noise makes the variance vary across the box: not separable"
    steps = np.arange(-half, half + 2, dtype=np.float64)
    cols = np.floor(x_px)[:, None] + steps[None, :]
    rows = np.floor(y_px)[:, None] + steps[None, :]
    in_cols = np.ones(cols.shape) if shape_px is None else ((cols >= 0) & (cols < shape_px[1])).astype(np.float64)
    in_rows = np.ones(rows.shape) if shape_px is None else ((rows >= 0) & (rows < shape_px[0])).astype(np.float64)
    px = pixel_integrated_gaussian(cols, x_px[:, None], sigma) * in_cols
    py = pixel_integrated_gaussian(rows, y_px[:, None], sigma) * in_rows
    dpx = pixel_integrated_gaussian_dsource(cols, x_px[:, None], sigma) * in_cols
    dpy = pixel_integrated_gaussian_dsource(rows, y_px[:, None], sigma) * in_rows
    # the x-factors and y-factors of the four columns of J: (N dPx, Px, Px, 1) along x, (Py, N dPy, Py, 1) along y
    n = flux_e[:, None]
    fx = np.stack([n * dpx, px, px, in_cols], axis=1)  # (stars, 4, columns)
    fy = np.stack([py, n * dpy, py, in_rows], axis=1)
    fisher = (fx @ np.swapaxes(fx, 1, 2)) * (fy @ np.swapaxes(fy, 1, 2)) / (noise_e**2)[:, None, None]
    cov = np.linalg.inv(fisher)
    return np.sqrt(np.maximum(cov[:, 0, 0], cov[:, 1, 1]))


def _crb_max_block(x_px, y_px, flux_e, sigma: float, noise_e, shot: bool, half: int, shape_px=None) -> np.ndarray:
    """:func:`_crb_max_px` of one block of stars."""
    steps = np.arange(-half, half + 2, dtype=np.float64)
    cols = np.floor(x_px)[:, None] + steps[None, :]
    rows = np.floor(y_px)[:, None] + steps[None, :]
    params = np.column_stack([x_px, y_px, flux_e, np.zeros_like(x_px)])
    mu, jac = psf_model_batch(cols, rows, params, sigma)
    if shape_px is not None:  # the pixels beyond the border carry no information
        h, w = shape_px
        outside = ~(((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :])
        if outside.any():
            jac = np.where(outside[..., None], 0.0, jac)
    variance = (mu if shot else 0.0) + (noise_e**2)[:, None, None]
    jac = jac.reshape(x_px.size, -1, 4)
    weighted = jac / variance.reshape(x_px.size, -1, 1)
    fisher = np.matmul(np.swapaxes(weighted, 1, 2), jac)  # J^T W J per star: a batched product, not a 3-way einsum
    cov = np.linalg.inv(fisher)
    return np.sqrt(np.maximum(cov[:, 0, 0], cov[:, 1, 1]))
