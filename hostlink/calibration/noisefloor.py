"""The centroid noise of stars of given ``sigma_px`` as two variance components: each star's 1-sigma noise per axis
sigma_i^2 = (s sigma_px_i)^2 + floor^2, a scale s of the given bound and an additive floor [px] common to the
session (what no Gaussian-PSF Cramer-Rao bound counts: JPEG blocks, PSF mismatch, lens residuals; figures:
docs/calibration.md), both estimated from the inliers' residuals of a fit.

Method: restricted maximum likelihood of variance components (Patterson and Thompson 1971, Biometrika 58, 545;
Koch 1999, Parameter Estimation and Hypothesis Testing in Linear Models, 2nd ed., sec. 3.6), with each star's
share of the degrees of freedom given by its redundancy number r_i = 2 - tr(H_ii) (Foerstner 1979, Allgemeine
Vermessungs-Nachrichten 86, 446: the diagonal of the redundancy matrix R = I - A N^-1 A^T W, 2 axes per star) in
place of the full projection: |e_i|^2 / v_i is taken as chi-square with r_i degrees of freedom, v_i = a sigma_px_i^2
+ b (a = s^2, b = floor^2). The likelihood is profiled over the ratio t = b / a >= 0 (for each t the scale is closed
form, a(t) = sum |e_i|^2 / u_i / sum r_i with u_i = sigma_px_i^2 + t), and t minimises
sum r_i log(a(t) u_i) over a log grid refined by golden section, t = 0 kept unless another is strictly better
(the floor is then not identifiable when every star has the same sigma_px: the scale takes all). The hat matrix
counts each frame's attitude (3 parameters, the bulk of them); the camera's K parameters are left out of it, K / 2N
of the degrees of freedom (< 1e-3 for the sessions calibrated). Standard errors: the inverse Fisher information of
(a, b), F_jk = 1/2 sum r_i (dv_i/da_j)(dv_i/da_k) / v_i^2.

The sums are kept per bin of log sigma_px (:data:`NOISE_BIN_WIDTH` wide), added over chunks, so a session of any
length is summarised in a few kilobytes and the result does not depend on how its frames are split.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from hostlink.calibration.data import SIGMA_PX_CEILING, SIGMA_PX_FLOOR, CalibrationData
from hostlink.calibration.frames import inverse_3x3
from hostlink.calibration.model import attitude_terms, camera_terms
from hostlink.calibration.normal import attitude_normal
from hostlink.calibration.passes import frame_attitudes
from hostlink.calibration.source import ChunkSource, without_rows

#: Width of a bin of ln(sigma_px): 0.5 %, so a bin's stars' variances agree within 1 % (v_i evaluated at the bin's
#: mean sigma_px^2: a relative error below 1e-4 in the weights of the likelihood).
NOISE_BIN_WIDTH = 0.005
_LN_LO = math.log(SIGMA_PX_FLOOR)
NOISE_BINS = int(math.ceil((math.log(SIGMA_PX_CEILING) - _LN_LO) / NOISE_BIN_WIDTH)) + 1
#: The profile's grid of t / median(sigma_px^2): 10^-6 to 10^6 (a floor from 1e-3 to 1e3 times the median given
#: noise), 10 points a decade, then golden section between the best point's neighbours to 1e-6 in ln t.
_GRID = np.logspace(-6.0, 6.0, 121)
_GOLDEN_TOL = 1e-6


@dataclass
class NoiseSums:
    """Per bin of ln sigma_px: sum of r_i, of |e_i|^2 [px^2] and of r_i sigma_px_i^2 [px^2]."""

    r: np.ndarray
    e2: np.ndarray
    r_s2: np.ndarray

    def merge(self, other: NoiseSums) -> NoiseSums:
        return NoiseSums(self.r + other.r, self.e2 + other.e2, self.r_s2 + other.r_s2)


def empty_noise_sums() -> NoiseSums:
    return NoiseSums(np.zeros(NOISE_BINS), np.zeros(NOISE_BINS), np.zeros(NOISE_BINS))


@dataclass(frozen=True)
class NoiseComponents:
    """The estimated components: ``scale`` s (a = s^2), ``floor_px`` (b = floor^2), the ratio ``t`` = b / a
    [px^2], the standard errors of a and b, and the degrees of freedom sum r_i."""

    scale: float
    floor_px: float
    t_px2: float
    a_sigma: float
    b_sigma_px2: float
    dof: float


def with_floor(data: CalibrationData, t_px2: float) -> CalibrationData:
    """``data`` with each star's noise sqrt(sigma_px^2 + t) (the floor relative to the scale, t = floor^2 / s^2): the
    noise the weights and the gate use, up to the fitted scale s. ``data`` itself when t is 0 or it has none."""
    if data.sigma_px is None or t_px2 <= 0.0:
        return data
    return replace(data, sigma_px=np.sqrt(data.sigma_px * data.sigma_px + t_px2))


def _load_with_floor(load, t_px2: float, handle) -> CalibrationData:
    return with_floor(handle if load is None else load(handle), t_px2)


def floored_source(source: ChunkSource, t_px2: float) -> ChunkSource:
    """``source`` whose chunks read :func:`with_floor` (spooled chunks on load, where a worker reads them)."""
    if t_px2 <= 0.0:
        return source
    if source.load is None:
        return ChunkSource(tuple(with_floor(h, t_px2) for h in source.handles))
    return ChunkSource(source.handles, partial(_load_with_floor, source.load, t_px2), source.count)


def chunk_noise_sums(data: CalibrationData, theta: np.ndarray, t_px2: float) -> NoiseSums:
    """The :class:`NoiseSums` of the stars of ``data`` (given sigma_px; the inliers) at the camera ``theta``: each
    frame's attitude fitted by weighted least squares (weights 1 / (sigma_px^2 + t); no Huber weights: the model's
    likelihood is Gaussian, and these are the inliers; with the fit's Huber weights at 3 robust sigmas the
    floor of a session without one came out ~10 of its standard errors high), the residual
    |e_i|^2 [px^2] and the redundancy r_i = 2 - tr(H_ii), H_ii = W_i J_i A_f^-1 J_i^T with A_f the frame's
    weighted attitude normal matrix."""
    out = empty_noise_sums()
    if data.n_frames == 0:
        return out
    fit = with_floor(data, t_px2)
    cam = camera_terms(fit.x_px, fit.y_px, theta)
    att = frame_attitudes(fit, theta, np.inf, 3.0, cam)
    e, jp = attitude_terms(fit.x_px, fit.y_px, fit.r, np.repeat(att, fit.counts, axis=0), theta, cam)
    inv = 1.0 / fit.sigma_px
    jw = jp * inv[:, None, None]
    a_inv = np.repeat(
        inverse_3x3(attitude_normal(e * inv[:, None], jw, np.ones(fit.n_obs), fit.frame_starts)[0]), fit.counts, axis=0
    )
    lever = np.einsum("nai,nij,naj->n", jw, a_inv, jw)
    r = np.maximum(2.0 - lever, 0.0)
    s2 = data.sigma_px * data.sigma_px
    idx = np.clip(((np.log(data.sigma_px) - _LN_LO) / NOISE_BIN_WIDTH).astype(np.int64), 0, NOISE_BINS - 1)
    e2 = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]
    return NoiseSums(
        np.bincount(idx, r, NOISE_BINS), np.bincount(idx, e2, NOISE_BINS), np.bincount(idx, r * s2, NOISE_BINS)
    )


def noise_sums(source: ChunkSource, theta: np.ndarray, dropped_rows: np.ndarray, t_px2: float) -> NoiseSums:
    """:func:`chunk_noise_sums` over the chunks of ``source`` (the given sigma_px, no floor), less ``dropped_rows``
    (sorted: voted and gated stars) and the frames they leave with fewer than three stars."""
    out = empty_noise_sums()
    for chunk in source:
        out = out.merge(chunk_noise_sums(without_rows(chunk, dropped_rows), theta, t_px2))
    return out


def _profile(r: np.ndarray, e2: np.ndarray, s2: np.ndarray, t: float) -> tuple[float, float]:
    """The profiled -2 log-likelihood (up to a constant) at the ratio t, and the scale a(t)."""
    u = s2 + t
    a = float(np.sum(e2 / u) / np.sum(r))
    return float(np.sum(r * np.log(a * u))), a


def variance_components(sums: NoiseSums) -> NoiseComponents:
    """The restricted maximum-likelihood (a, b) of the module docstring from the binned sums (the floor at the
    boundary t = 0 unless a positive ratio is strictly more likely)."""
    keep = sums.r > 0
    r, e2 = sums.r[keep], sums.e2[keep]
    s2 = sums.r_s2[keep] / r
    if r.size == 0 or np.sum(e2) <= 0.0:
        raise ValueError("no residual to estimate the noise from")
    median = float(np.median(s2))
    best_t, (best_l, _) = 0.0, _profile(r, e2, s2, 0.0)
    grid = _GRID * median
    values = [_profile(r, e2, s2, t)[0] for t in grid]
    k = int(np.argmin(values))
    tol = 1e-12 * abs(best_l) + 1e-12
    if values[k] < best_l - tol:
        lo, hi = math.log(grid[max(k - 1, 0)]), math.log(grid[min(k + 1, grid.size - 1)])
        g = (math.sqrt(5.0) - 1.0) / 2.0
        while hi - lo > _GOLDEN_TOL:
            c, d = hi - g * (hi - lo), lo + g * (hi - lo)
            if _profile(r, e2, s2, math.exp(c))[0] < _profile(r, e2, s2, math.exp(d))[0]:
                hi = d
            else:
                lo = c
        t = math.exp(0.5 * (lo + hi))
        value = _profile(r, e2, s2, t)[0]
        if value < best_l - tol:
            best_t, best_l = t, value
    a = _profile(r, e2, s2, best_t)[1]
    b = a * best_t
    v = a * s2 + b
    fisher = 0.5 * np.array(
        [[np.sum(r * s2 * s2 / v**2), np.sum(r * s2 / v**2)], [np.sum(r * s2 / v**2), np.sum(r / v**2)]]
    )
    try:
        cov = np.linalg.inv(fisher)
        a_sigma, b_sigma = float(np.sqrt(max(cov[0, 0], 0.0))), float(np.sqrt(max(cov[1, 1], 0.0)))
    except np.linalg.LinAlgError:  # every star of one sigma_px: the two components are not separable
        a_sigma, b_sigma = float("inf"), float("inf")
    return NoiseComponents(math.sqrt(a), math.sqrt(b), best_t, a_sigma, b_sigma, float(np.sum(r)))


#: Fits of the camera with the floor re-estimated in between: the floor found after the first (no floor) is within
#: a few per cent of the next one's, which then changes no star's noise by more than :data:`FLOOR_SETTLED`.
MAX_FLOOR_FITS = 3
#: The floor has settled when the new one changes no star's noise (sqrt(sigma_px^2 + t)) by more than this share:
#: weights within 10 %, an efficiency loss of the order of 1e-3 (the loss is quadratic in the weights' error).
FLOOR_SETTLED = 0.05


def floor_settled(sums: NoiseSums, t_old_px2: float, t_new_px2: float) -> bool:
    """Whether going from the ratio ``t_old`` to ``t_new`` changes no star's noise by more than
    :data:`FLOOR_SETTLED` (over the stars of ``sums``)."""
    keep = sums.r > 0
    s2 = sums.r_s2[keep] / sums.r[keep]
    change = np.sqrt((s2 + t_new_px2) / (s2 + t_old_px2))
    return bool(np.all(np.abs(change - 1.0) <= FLOOR_SETTLED))
