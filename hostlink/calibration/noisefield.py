"""A noise floor that grows towards the edge of the field: each star's variance per axis
v_i = a sigma_px_i^2 + b + c q_i, q_i = (rho_i / rho_max)^2 its squared field radius from the nominal principal point
relative to the half-diagonal of the image (a = s^2, floor(q)^2 = b + c q [px^2]).

Why this form: the aberrations that grow off axis in a wide lens are, to lowest order (Seidel), coma, whose blur
(and so the centroid error it adds, for the stars' random colour, focus and sampling) grows linearly with the field
radius, and astigmatism and field curvature, which grow with its square; a centroid error linear in rho adds a
variance in rho^2, and the constant b is what is the same everywhere (JPEG blocks, PSF mismatch). A variance in
rho^4 (the astigmatism's blur) is the next term; two parameters are what nine frames of a few hundred stars can
determine.

Estimation: the restricted likelihood of :mod:`hostlink.calibration.noisefloor` (|e_i|^2 / v_i chi-square with
r_i degrees of freedom, -2 log L = sum r_i log v_i + |e_i|^2 / v_i up to a constant) in the three components,
maximised by Fisher scoring (the iterated REML estimate of variance components: theta = F^-1 h with
F_kl = sum r_i T_ki T_li / v_i^2 and h_k = sum |e_i|^2 T_ki / v_i^2, T_i = (sigma_px_i^2, 1, q_i); Koch 1999, sec.
3.6.3; Foerstner 1979) under b, c >= 0 (an active set: a component that would go negative is held at 0, and freed
again when the likelihood's gradient points inward), with a halved step whenever a full one would not lower -2 log L.

Choice: the constant floor (c = 0) is the null hypothesis, on the boundary of the radial one. With the centre floor
b > 0 (a nuisance parameter inside its range) the likelihood-ratio statistic LR = (-2 log L)_constant -
(-2 log L)_radial is distributed as an equal mixture of chi-square with 0 and 1 degrees of freedom under it (Self and
Liang 1987, J. Am. Stat. Assoc. 82, 605: one parameter of interest on the boundary, the nuisance parameters
inside): 9.55 (:data:`LR_CRITICAL`) is its 1e-3 point. With no floor at all (b = 0, the nuisance on its boundary as
well) the distribution depends on the angle phi between the b and c directions in the Fisher metric (profiled over
a; Self and Liang's geometry, :func:`boundary_tail`): below the equal mixture for phi < 90 deg (sigma_px unrelated
to the field radius: the 1e-3 point 5.1 at phi = 35 deg), above it for phi > 90 deg (sigma_px growing with the
radius: 2.4e-3 at 9.55 for phi = 148 deg). The radial floor is chosen when LR exceeds the larger of the two 1e-3
points (:func:`lr_critical`): at most a 1e-3 chance of choosing it for a session whose floor is constant, in both
limits (b = 0, and b many standard errors above 0; asymptotically, as every rate here).
"""

from __future__ import annotations

import math

import numpy as np

#: The 0.999 quantile of the 50:50 mixture of chi-square(0) and chi-square(1): 0.5 P(chi2_1 > x) = 1e-3, i.e. the
#: chi-square(1) 0.998 quantile (scipy.stats.chi2.isf(0.002, 1) = 9.5495).
LR_CRITICAL = 9.5495
#: Fisher scoring stops when no component moves by more than this share of the largest variance's size.
_SCORING_TOL = 1e-10
_MAX_SCORING = 200
#: Beyond this condition number of the Fisher information two components are not separable (sigma_px^2 and 1 are
#: then proportional: their columns agree to ~1e-8 of their size, below what float64 sums resolve in F).
_SEPARABLE_COND = 1e12


def minus_two_log_l(r: np.ndarray, e2: np.ndarray, t: np.ndarray, theta: np.ndarray) -> float:
    """-2 log of the restricted likelihood (up to a constant) of the components ``theta`` (a, b, c) over bins of
    redundancy ``r``, squared residuals ``e2`` and regressors ``t`` (n, 3): sum r log v + e2 / v, v = t theta."""
    v = t @ theta
    return float(np.sum(r * np.log(v) + e2 / v))


def _scoring_step(r: np.ndarray, e2: np.ndarray, t: np.ndarray, theta: np.ndarray, free: np.ndarray) -> np.ndarray:
    """theta after one Fisher-scoring step over the ``free`` components (the others held at 0)."""
    v = t @ theta
    tf = t[:, free]
    info = 2.0 * fisher_information(r, tf, v)  # F and h both without their factor 1/2 (exact: a power of two)
    h = tf.T @ (e2 / v**2)
    out = np.zeros(3)
    out[free] = np.linalg.lstsq(info, h, rcond=None)[0]
    return out


def _gradient(r: np.ndarray, e2: np.ndarray, t: np.ndarray, theta: np.ndarray) -> np.ndarray:
    v = t @ theta
    return t.T @ (r / v - e2 / v**2)


def _free_target(r: np.ndarray, e2: np.ndarray, t: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """The scoring step's target over the components the likelihood lets move: those above 0, and those at 0 whose
    gradient points inward; one at 0 whose target would be negative is held there and the target solved again (a
    set with none free, every v_i at 0, cannot arise: the start has a v_i > 0 and steps keep it)."""
    free = (theta > 0.0) | (_gradient(r, e2, t, theta) < 0.0)
    while True:
        target = _scoring_step(r, e2, t, theta, free)
        stuck = free & (theta <= 0.0) & (target < 0.0)
        if not np.any(stuck):
            return target
        free &= ~stuck


def radial_components(r: np.ndarray, e2: np.ndarray, t: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The restricted maximum-likelihood (a, b, c) >= 0 (every v_i > 0) of the module docstring, by Fisher scoring
    from ``start`` (the constant floor's estimate, c = 0): each step goes towards :func:`_free_target`, stopped where
    a component reaches 0 (held there while the likelihood wants it lower), and halved until -2 log L does not
    rise."""
    theta = np.asarray(start, dtype=np.float64).copy()
    best = minus_two_log_l(r, e2, t, theta)
    for _ in range(_MAX_SCORING):
        step = _free_target(r, e2, t, theta) - theta
        down = step < 0.0
        to_zero = np.full(3, math.inf)
        to_zero[down] = theta[down] / -step[down]
        lam = min(1.0, float(np.min(to_zero)))
        # the components whose path reaches 0 first are set to exactly 0 (theta + lam step leaves them a rounding
        # error either side, and one left at 1e-20 would end the loop below on a step that moved nothing)
        reach = to_zero <= lam
        while True:
            trial = np.maximum(theta + lam * step, 0.0)
            trial[reach] = 0.0
            value = minus_two_log_l(r, e2, t, trial) if np.all(t @ trial > 0.0) else math.inf
            if value <= best or lam < 1e-6:
                break
            lam *= 0.5
            reach = to_zero <= lam
        if value > best:
            break
        # converged when the full step to the target is negligible, not the move: a step cut short at the boundary
        # moves little while the free components are still far from their maximum
        theta, best = trial, value
        if float(np.max(np.abs(step))) <= _SCORING_TOL * float(np.max(t @ theta)):
            break
    return theta


#: The false-alarm rate the choice is held to, and the polar grid :func:`boundary_tail` integrates over (the integrand
#: is smooth between the 4 region boundaries: 20000 points give the tail to ~1e-7 of itself).
FALSE_ALARM = 1e-3
_ANGLES = 20_000


def boundary_tail(x: float, phi_rad: float) -> float:
    """P(LR > x) under b = c = 0, asymptotically: Z ~ N(0, I) in the plane whitened by the profiled Fisher metric,
    the null cone the b ray (polar angle 0), the alternative the wedge between it and the c ray (angle ``phi_rad``);
    LR = d(Z, null)^2 - d(Z, wedge)^2 = R^2 g(theta) with R^2 ~ chi-square(2) independent of the uniform theta, so
    P(LR > x) = mean over theta of exp(-x / (2 g(theta))) (Self and Liang 1987, sec. 3: the projections onto the
    cones). g: sin^2 theta (1 past 90 deg) inside the wedge; that less sin^2(theta - phi) within 90 deg beyond the c
    ray; 0 elsewhere (both projections the same)."""
    return _tail(x, *_polar_gap(phi_rad))


def _polar_gap(phi_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Where g of :func:`boundary_tail` is positive on its polar grid, and 2 g there (x-independent: computed once
    for the whole bisection of :func:`_boundary_critical`)."""
    theta = (np.arange(_ANGLES, dtype=np.float64) + 0.5) * (2.0 * math.pi / _ANGLES)
    to_null = np.where(theta <= 0.5 * math.pi, np.sin(theta) ** 2, 1.0)
    g = np.where(theta <= phi_rad, to_null, 0.0)
    beyond = (theta > phi_rad) & (theta <= phi_rad + 0.5 * math.pi)
    g = np.where(beyond, to_null - np.sin(theta - phi_rad) ** 2, g)
    return g > 0.0, 2.0 * np.maximum(g, 1e-300)


def _tail(x: float, positive: np.ndarray, two_g: np.ndarray) -> float:
    """:func:`boundary_tail` at ``x`` from :func:`_polar_gap`."""
    with np.errstate(divide="ignore"):
        tail = np.where(positive, np.exp(-x / two_g), 0.0)
    return float(np.mean(tail))


def _boundary_critical(phi_rad: float) -> float:
    """The x where :func:`boundary_tail` is :data:`FALSE_ALARM` (bisection to 1e-6; the tail falls with x)."""
    gap = _polar_gap(phi_rad)
    lo, hi = 0.0, 50.0
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _tail(mid, *gap) > FALSE_ALARM else (lo, mid)
    return 0.5 * (lo + hi)


def lr_critical(r: np.ndarray, t: np.ndarray, theta: np.ndarray) -> float:
    """The likelihood ratio above which the radial floor is chosen, for the bins ``r``, regressors ``t`` and the
    constant floor's estimate ``theta`` (a, b, 0): the larger of :data:`LR_CRITICAL` (b > 0) and the 1e-3 point of
    :func:`boundary_tail` (b = 0) at the angle between b and c in the Fisher information profiled over a (its Schur
    complement). :data:`LR_CRITICAL` when a and b cannot be told apart (every star of one sigma_px: a sigma_px^2 + b
    is then one component inside its range, the case of the equal mixture)."""
    fisher = fisher_information(r, t, t @ theta)
    if not _separable(fisher):
        return LR_CRITICAL
    m = fisher[1:, 1:] - np.outer(fisher[1:, 0], fisher[0, 1:]) / fisher[0, 0]
    phi = math.acos(max(-1.0, min(1.0, m[0, 1] / math.sqrt(m[0, 0] * m[1, 1]))))
    return max(LR_CRITICAL, _boundary_critical(phi))


def fisher_information(r: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The Fisher information of the components whose regressors are the columns of ``t`` (n, k), over bins of
    redundancy ``r`` and variance ``v``: F_kl = 1/2 sum r_i T_ki T_li / v_i^2 (|e_i|^2 / v_i chi-square with r_i
    degrees of freedom; Koch 1999, sec. 3.6.3)."""
    return 0.5 * (t * (r / v**2)[:, None]).T @ t


def _separable(fisher: np.ndarray) -> bool:
    """Whether the components of ``fisher`` can be told apart: the condition number of its correlation form (scaled
    to a unit diagonal, so the components' units do not count) within :data:`_SEPARABLE_COND`."""
    d = np.sqrt(np.diag(fisher))
    return bool(np.all(d > 0.0) and np.linalg.cond(fisher / np.outer(d, d)) <= _SEPARABLE_COND)


def fisher_errors(r: np.ndarray, t: np.ndarray, theta: np.ndarray, free: np.ndarray) -> np.ndarray:
    """Standard errors of the ``free`` components: the square roots of the diagonal of the inverse Fisher information
    F_kl = 1/2 sum r_i T_ki T_li / v_i^2; 0 for the others. When a and b cannot be told apart (every star of one
    sigma_px: :func:`_separable`) theirs are inf, as for the constant floor, and
    c's is that of the two separable components (a sigma_px^2 + b, c)."""
    v = t @ theta
    fisher = fisher_information(r, t[:, free], v)
    out = np.zeros(3)
    if _separable(fisher):
        out[free] = np.sqrt(np.maximum(np.diag(np.linalg.inv(fisher)), 0.0))
        return out
    out[:2] = math.inf
    fisher_c = fisher_information(r, t[:, 1:], v)
    if free[2] and _separable(fisher_c):
        out[2] = math.sqrt(max(np.linalg.inv(fisher_c)[1, 1], 0.0))
    elif free[2]:
        out[2] = math.inf
    return out
