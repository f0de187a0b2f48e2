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

The sums are kept per occupied bin of ln sigma_px (:data:`NOISE_BIN_WIDTH` wide) and of q, the squared field radius
relative to the half-diagonal (:data:`Q_BIN_WIDTH` wide), added over chunks, so a session of any length is summarised
in at most one entry per occupied bin (a few hundred kilobytes at most) and the result does not depend on how its
frames are split. From the same sums :func:`variance_components` also fits a floor that grows with the field radius
(floor^2 = b + c q, :mod:`hostlink.calibration.noisefield`) and keeps it when the likelihood ratio says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from hostlink.calibration.data import SIGMA_PX_CEILING, SIGMA_PX_FLOOR, CalibrationData
from hostlink.calibration.frames import inverse_3x3
from hostlink.calibration.model import attitude_terms, camera_terms, half_diagonal_px
from hostlink.calibration.noisefield import LR_CRITICAL, fisher_errors, lr_critical, minus_two_log_l, radial_components
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


#: Width of a bin of q, the squared field radius relative to the half-diagonal (:mod:`hostlink.calibration.
#: noisefield`): 1/32, so the radial term c q varies within a bin by c / 32, its weight by at most 3 % at the corner
#: where it is all the variance, a relative error of ~1e-3 in the likelihood's terms (second order in the spread);
#: near the centre a b below c / 32 spreads the first bins more, but few stars lie there: 4096 bins instead moved b
#: and c by 0.1 of their standard errors on the simulated sessions of docs/calibration.md.
Q_BIN_WIDTH = 1.0 / 32.0
#: q up to 2 (a principal point off the centre puts far corners beyond the half-diagonal); beyond, the last bin.
Q_BINS = 64


@dataclass(frozen=True)
class NoiseModel:
    """The noise the weights use, relative to the fitted scale s: each star's sqrt(sigma_px^2 + t + t_edge q), q its
    squared distance from ``center_px`` over ``r_max_px``^2 (the floor^2 / s^2 at the centre and its growth to
    q = 1, [px^2])."""

    t_px2: float = 0.0
    t_edge_px2: float = 0.0
    center_px: tuple[float, float] = (0.0, 0.0)
    r_max_px: float = 1.0


def field_geometry(params) -> NoiseModel:
    """A model without floor whose field radius is taken from the principal point of ``params`` (the nominal: the
    same for every fit) relative to the half-diagonal of its image."""
    return NoiseModel(0.0, 0.0, tuple(float(c) for c in params.principal_point_px), half_diagonal_px(params))


def field_q(data: CalibrationData, noise: NoiseModel) -> np.ndarray:
    """(N,) each star's squared field radius relative to the half-diagonal."""
    dx, dy = data.x_px - noise.center_px[0], data.y_px - noise.center_px[1]
    return (dx * dx + dy * dy) / (noise.r_max_px * noise.r_max_px)


@dataclass
class NoiseSums:
    """Per occupied bin (``key``: the bin of ln sigma_px times :data:`Q_BINS` plus the bin of q): sum of r_i, of
    |e_i|^2 [px^2], of r_i sigma_px_i^2 [px^2] and of r_i q_i."""

    key: np.ndarray
    r: np.ndarray
    e2: np.ndarray
    r_s2: np.ndarray
    r_q: np.ndarray

    def merge(self, other: NoiseSums) -> NoiseSums:
        return _reduced(*(np.concatenate([a, b]) for a, b in zip(self.columns(), other.columns(), strict=True)))

    def columns(self) -> tuple[np.ndarray, ...]:
        return self.key, self.r, self.e2, self.r_s2, self.r_q


def _reduced(key: np.ndarray, *values: np.ndarray) -> NoiseSums:
    """The sums of ``values`` per distinct ``key``."""
    keys, inverse = np.unique(key, return_inverse=True)
    return NoiseSums(keys, *(np.bincount(inverse, v, keys.size) for v in values))


def empty_noise_sums() -> NoiseSums:
    return NoiseSums(np.zeros(0, np.int64), *(np.zeros(0) for _ in range(4)))


@dataclass(frozen=True)
class NoiseComponents:
    """The estimated components: ``scale`` s (a = s^2), ``floor_px`` (b = floor^2 at the centre), the ratio ``t`` =
    b / a [px^2], the standard errors of a and b, the degrees of freedom sum r_i; the radial term ``edge_px2`` c
    (floor(q)^2 = b + c q, 0 for the constant model), its standard error, ``model`` ("constant" or "radial", as
    chosen), the likelihood-ratio statistic ``lr`` of the radial model against the constant one and the
    ``lr_critical`` it was held to (:func:`~hostlink.calibration.noisefield.lr_critical`)."""

    scale: float
    floor_px: float
    t_px2: float
    a_sigma: float
    b_sigma_px2: float
    dof: float
    edge_px2: float = 0.0
    c_sigma_px2: float = 0.0
    model: str = "constant"
    lr: float = 0.0
    lr_critical: float = LR_CRITICAL

    def weights(self, geometry: NoiseModel) -> NoiseModel:
        """The :class:`NoiseModel` of these components on the field ``geometry``."""
        return replace(geometry, t_px2=self.t_px2, t_edge_px2=self.edge_px2 / self.scale**2)


def with_floor(data: CalibrationData, noise: NoiseModel) -> CalibrationData:
    """``data`` with each star's noise sqrt(sigma_px^2 + t + t_edge q) (the floor relative to the scale, t = floor^2 /
    s^2): the noise the weights and the gate use, up to the fitted scale s. ``data`` itself when there is no floor
    or no sigma_px."""
    if data.sigma_px is None or not _has_floor(noise):
        return data
    added = noise.t_px2 + (noise.t_edge_px2 * field_q(data, noise) if noise.t_edge_px2 > 0.0 else 0.0)
    return replace(data, sigma_px=np.sqrt(data.sigma_px * data.sigma_px + added))


def _load_with_floor(load, noise: NoiseModel, handle) -> CalibrationData:
    return with_floor(handle if load is None else load(handle), noise)


def _has_floor(noise: NoiseModel) -> bool:
    return noise.t_px2 > 0.0 or noise.t_edge_px2 > 0.0


def floored_source(source: ChunkSource, noise: NoiseModel) -> ChunkSource:
    """``source`` whose chunks read :func:`with_floor` (spooled chunks on load, where a worker reads them)."""
    if not _has_floor(noise):
        return source
    if source.load is None:
        return ChunkSource(tuple(with_floor(h, noise) for h in source.handles))
    return ChunkSource(source.handles, partial(_load_with_floor, source.load, noise), source.count)


def chunk_noise_sums(data: CalibrationData, theta: np.ndarray, noise: NoiseModel) -> NoiseSums:
    """The :class:`NoiseSums` of the stars of ``data`` (given sigma_px; the inliers) at the camera ``theta``: each
    frame's attitude fitted by weighted least squares (weights 1 / (sigma_px^2 + t + t_edge q); no Huber weights: the
    model's likelihood is Gaussian, and these are the inliers; with the fit's Huber weights at 3 robust sigmas the
    floor of a session without one came out ~10 of its standard errors high), the residual
    |e_i|^2 [px^2] and the redundancy r_i = 2 - tr(H_ii), H_ii = W_i J_i A_f^-1 J_i^T with A_f the frame's
    weighted attitude normal matrix."""
    if data.n_frames == 0:
        return empty_noise_sums()
    fit = with_floor(data, noise)
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
    q = field_q(data, noise)
    idx = np.clip(((np.log(data.sigma_px) - _LN_LO) / NOISE_BIN_WIDTH).astype(np.int64), 0, NOISE_BINS - 1)
    key = idx * Q_BINS + np.clip((q / Q_BIN_WIDTH).astype(np.int64), 0, Q_BINS - 1)
    e2 = e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]
    return _reduced(key, r, e2, r * s2, r * q)


def noise_sums(source: ChunkSource, theta: np.ndarray, dropped_rows: np.ndarray, noise: NoiseModel) -> NoiseSums:
    """:func:`chunk_noise_sums` over the chunks of ``source`` (the given sigma_px, no floor), less ``dropped_rows``
    (sorted: voted and gated stars) and the frames they leave with fewer than three stars."""
    out = empty_noise_sums()
    for chunk in source:
        out = out.merge(chunk_noise_sums(without_rows(chunk, dropped_rows), theta, noise))
    return out


def _profile(r: np.ndarray, e2: np.ndarray, s2: np.ndarray, t: float) -> tuple[float, float]:
    """The profiled -2 log-likelihood (up to a constant) at the ratio t, and the scale a(t)."""
    u = s2 + t
    a = float(np.sum(e2 / u) / np.sum(r))
    return float(np.sum(r * np.log(a * u))), a


def _constant_ratio(r: np.ndarray, e2: np.ndarray, s2: np.ndarray) -> float:
    """The ratio t = b / a of the constant floor maximising the profile (0 unless another is strictly better)."""
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
            best_t = t
    return best_t


def _binned(sums: NoiseSums) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    keep = sums.r > 0
    r = sums.r[keep]
    return r, sums.e2[keep], sums.r_s2[keep] / r, sums.r_q[keep] / r


def variance_components(sums: NoiseSums, radial: bool = True) -> NoiseComponents:
    """The restricted maximum-likelihood components from the binned sums: the constant floor's (a, b) of the module
    docstring (the floor at the boundary t = 0 unless a positive ratio is strictly more likely), and with ``radial``
    the (a, b, c) of :mod:`hostlink.calibration.noisefield` from there, chosen when its likelihood ratio exceeds
    :func:`~hostlink.calibration.noisefield.lr_critical` (:data:`~hostlink.calibration.noisefield.LR_CRITICAL`, or
    more when the floor may be 0 and sigma_px grows with the field radius; no further pass over the data: the same
    sums)."""
    r, e2, s2, q = _binned(sums)
    if r.size == 0 or np.sum(e2) <= 0.0:
        raise ValueError("no residual to estimate the noise from")
    t = _constant_ratio(r, e2, s2)
    a = _profile(r, e2, s2, t)[1]
    b = a * t
    regressors = np.column_stack([s2, np.ones_like(s2), q])
    # inf when every star has one sigma_px (a and b not separable; the inverse of the singular information had
    # stated 0 +- 0 before)
    a_sigma, b_sigma, _ = fisher_errors(r, regressors, np.array([a, b, 0.0]), np.array([True, True, False]))
    constant = NoiseComponents(math.sqrt(a), math.sqrt(b), t, float(a_sigma), float(b_sigma), float(np.sum(r)))
    if not radial:
        return constant
    theta = radial_components(r, e2, regressors, np.array([a, b, 0.0]))
    lr = minus_two_log_l(r, e2, regressors, np.array([a, b, 0.0])) - minus_two_log_l(r, e2, regressors, theta)
    critical = lr_critical(r, regressors, np.array([a, b, 0.0]))
    if not (lr > critical and theta[2] > 0.0):
        return replace(constant, lr=max(lr, 0.0), lr_critical=critical)
    err = fisher_errors(r, regressors, theta, np.ones(3, dtype=bool))  # at a boundary b = 0 too: its local spread
    a, b, c = (float(x) for x in theta)
    return NoiseComponents(
        math.sqrt(a),
        math.sqrt(b),
        b / a,
        float(err[0]),
        float(err[1]),
        float(np.sum(r)),
        c,
        float(err[2]),
        "radial",
        lr,
        critical,
    )


#: Fits of the camera with the floor re-estimated in between: the floor found after the first (no floor) is within
#: a few per cent of the next one's, which then changes no star's noise by more than :data:`FLOOR_SETTLED`.
MAX_FLOOR_FITS = 3
#: The floor has settled when the new one changes no star's noise (sqrt(sigma_px^2 + t)) by more than this share:
#: weights within 10 %, an efficiency loss of the order of 1e-3 (the loss is quadratic in the weights' error).
FLOOR_SETTLED = 0.05


def floor_settled(sums: NoiseSums, old: NoiseModel, new: NoiseModel, share: float = FLOOR_SETTLED) -> bool:
    """Whether going from the noise model ``old`` to ``new`` changes no star's noise by more than ``share``
    (over the bins of ``sums``, at each bin's mean sigma_px^2 and q)."""
    _, _, s2, q = _binned(sums)
    change = np.sqrt((s2 + new.t_px2 + new.t_edge_px2 * q) / (s2 + old.t_px2 + old.t_edge_px2 * q))
    return bool(np.all(np.abs(change - 1.0) <= share))
