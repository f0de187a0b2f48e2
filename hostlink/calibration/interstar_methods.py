"""Seed 000's interstar-angle calibrations: cosine and sine least squares, and the improved two-step iteration.

Observation equations (seed 000 eq. 3): for stars i, j of one frame,
    cosine:  cos(theta_ij) = r_i . r_j = b_i . b_j                                   (eq. 3a)
    sine:    sin(theta_ij) = |r_i x r_j| = |b_i x b_j|                               (eq. 3b, eq. 4-6)
with b from the camera model (seed 000 eq. 2 and 7 are ``onboard.camera``). The cosine residual is evaluated in the
difference form of ``onboard.interstar`` (r_i . r_j - b_i . b_j = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2, the same
number without the cancellation of 1 - cos).

Weighting (issue 3): the paper stacks all n(n-1)/2 pairs of a frame as independent rows (eq. 8-12). Only 2n - 3
of them are independent, and they are correlated through shared stars. Here each frame contributes the 2n - 3 pairs
of ``onboard.interstar.independent_pairs`` whitened by their covariance from centroid noise
(``onboard.interstar.pair_covariance``, for the sine form propagated by d sin = -cot(theta) d cos), which is the
generalised least-squares form of eq. 13: dtheta = (A^T P^-1 A)^-1 A^T P^-1 R, iterated (Gauss-Newton).

Methods:
- ``cosine`` / ``sine``: the batch least squares of seed 000 Table 1 columns 1-2 (after Samaan et al. 2001 and the
  paper's ref. 11): focal length and principal point only, distortion held at its nominal value.
- ``improved-cosine`` / ``improved-sine`` (seed 000 sec. 2): (1) distortion 0, estimate (x0, y0, f) from stars
  near the field centre (sec. 4.1: the first estimate uses the central field, where distortion is small);
  (2) with (x0, y0, f) fixed, estimate the Weng distortion; (3) with the distortion fixed, re-estimate
  (x0, y0, f); repeat (2)-(3) (6 rounds: the paper's estimates are stable after 6 iterations, Fig. 2-3).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks
from hostlink.calibration.lm import COST_ROUNDING, DAMPING_FLOOR, DAMPING_GROWTH, INITIAL_DAMPING, MAX_DAMPING_TRIALS
from hostlink.calibration.model import DEFAULT_CHUNK_OBS, parameter_columns, parameter_scales
from hostlink.calibration.normal import covariance_from_normal, solve_scaled
from onboard.camera import unit_vector_jacobians
from onboard.interstar import (
    difference_jacobian,
    difference_residuals,
    independent_pairs,
    order_for_pairs,
    pair_covariance,
)
from onboard.params import ESTIMATE_NAMES, CameraParams

OPTICAL = ("f", "x0", "y0")
DISTORTION = tuple(n for n in ESTIMATE_NAMES if n not in OPTICAL)
#: Rounds of steps (2)-(3) of the improved method (seed 000 sec. 4.1: stable after 6 iterations).
IMPROVED_ROUNDS = 6
#: the alternation counts as converged when a joint Gauss-Newton step from where it stands is below this many joint
#: sigmas (it is then that close to its fixed point, the joint minimum: no reported digit of significance changes).
#: The step of the last round is no such measure: where the blocks trade off, rounds move little while far away
ALTERNATION_CONVERGED_SIGMAS = 0.1
#: Most entries of the pair-covariance gradients (frames x pairs x 2 stars' coordinates) built at once: bounds the
#: working memory of a batch of frames with the same star count (~16 MB per array in float64).
PAIR_BLOCK_ELEMENTS = 2_000_000
#: Levenberg-Marquardt of the seed methods (seed 004 sec. 2.1 and 2.3, after More 1978): the damping starts at this
#: fraction of the diagonal (More's customary start), then grows and shrinks as the bundle's does
#: (:mod:`hostlink.calibration.lm`)
START_DAMPING = 1e-3
#: A seed method's stage ends at a step below this size sqrt(dx^T N dx), N for unit centroid noise [px]: for a noise
#: of sigma px that is 1e-4 / sigma of the estimate's standard deviation (2e-3 of it at 0.05 px), below any
#: reported digit
STEP_TOL_UNIT_NOISE = 1e-4
#: Stars used by the first step of the improved method: within this fraction of the half-diagonal from the centre.
CENTRAL_FRACTION = 0.5


@dataclass
class InterstarFit:
    theta: np.ndarray
    estimate: tuple[str, ...]
    normal: np.ndarray  # (K, K) whitened normal matrix for unit noise, model-vector units
    sigma_estimated_px: float
    history: list[dict] = field(default_factory=list)
    stages: list[dict] = field(default_factory=list)  # per-step results (name, theta) for reports and tests
    #: how far a joint Gauss-Newton step from the result would move the camera, in standard deviations of the joint
    #: problem (:func:`newton_step_sigmas`); the improved methods have reached their fixed point only when it is small
    last_round_step_sigmas: float = 0.0
    converged: bool = True
    #: why a fit that did not converge stopped, naming what its model cannot separate (None when converged)
    failure: str | None = None


def frame_pair_orders(data: CalibrationData) -> np.ndarray:
    """(N,) global rows, frame by frame, each frame in the order ``order_for_pairs`` gives it (a well-separated base
    pair first): the rows of frame f in pair order are ``orders[frame_starts[f]:frame_starts[f + 1]]``.

    Frames with the same star count are ordered together (one batched call per count and block of frames), so the
    time is linear in frames and the working memory bounded by ``PAIR_BLOCK_ELEMENTS``."""
    orders = np.arange(data.n_obs, dtype=np.int64)
    counts = data.counts
    for n in np.unique(counts[counts >= 3]):
        n = int(n)
        frames = np.flatnonzero(counts == n)
        step = max(PAIR_BLOCK_ELEMENTS // n, 1)
        for c in range(0, frames.size, step):
            rows = data.frame_starts[frames[c : c + step], None] + np.arange(n)  # (m, n) global rows
            local = order_for_pairs(data.x_px[rows], data.y_px[rows]).astype(np.int64)
            orders[rows] = np.take_along_axis(rows, local, axis=1)
    return orders


def _sine_terms(b, r, jb, i, j):
    """Sine-form residual z - h (seed 000 eq. 4) and dh/dtheta for h = |b_i x b_j|, plus the factor
    d sin / d(cos - 1) = -cot(theta_ij) that carries the difference-form covariance over."""
    c = np.cross(b[i], b[j])
    h = np.linalg.norm(c, axis=1)
    z = np.linalg.norm(np.cross(r[i], r[j]), axis=1)
    u = c / h[:, None]
    # d(b_i x b_j) = db_i x b_j + b_i x db_j, contracted with u: u . (db_i x b_j) = (b_j x u) . db_i
    dh = np.einsum("pc,pck->pk", np.cross(b[j], u), jb[i]) + np.einsum("pc,pck->pk", np.cross(u, b[i]), jb[j])
    cos = np.sum(b[i] * b[j], axis=1)
    return z - h, dh, -cos / h


def interstar_normals(
    data: CalibrationData,
    theta: np.ndarray,
    cols: np.ndarray,
    form: str,
    orders: np.ndarray,
    col_scale: np.ndarray,
    frame_mask: np.ndarray | None = None,
    chunk_obs: int = DEFAULT_CHUNK_OBS,
    weight_theta: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Whitened normal equations of the interstar observation equations over every frame.

    The pair covariances P are evaluated at ``weight_theta`` (default: ``theta``). Holding them at the current
    iterate while a trial step is judged makes the fit iteratively reweighted least squares: letting P follow theta
    inside the cost lets the optimiser lower e^T P^-1 e by inflating P (P scales like F^-2), which biases f and the
    radial terms by an amount that does not shrink with more frames.

    Returns (N, g, cost, n_pairs): N = sum H^T P^-1 H, g = sum H^T P^-1 e (columns scaled by ``col_scale``),
    cost = sum e^T P^-1 e for unit centroid noise, with e = z - h (observed minus predicted) and H = dh/dtheta.
    ``orders`` from :func:`frame_pair_orders`. Frames with fewer than 3 stars (or masked out) contribute nothing.

    Vectorised over frames: per chunk of at most ``chunk_obs`` stars the camera Jacobians are evaluated once, the
    residuals and Jacobians of every frame's 2n - 3 pairs come from one call on pair index arrays offset by frame,
    and the pair covariances and their solves are batched over frames with the same star count (blocks of at most
    ``PAIR_BLOCK_ELEMENTS`` covariance-gradient entries). Memory is bounded by the chunk, time linear in frames.
    """
    k = cols.size
    normal = np.zeros((k, k))
    grad = np.zeros(k)
    cost = 0.0
    n_pairs = 0
    starts = data.frame_starts
    counts = data.counts
    usable = counts >= 3
    if frame_mask is not None:
        usable &= np.asarray(frame_mask, dtype=bool)
    for f0, f1 in frame_chunks(starts, chunk_obs):
        chunk_counts = np.where(usable[f0:f1], counts[f0:f1], 0)
        if not np.any(chunk_counts):
            continue
        a0, a1 = int(starts[f0]), int(starts[f1])
        b_all, jb_all, jc_all = unit_vector_jacobians(data.x_px[a0:a1], data.y_px[a0:a1], theta)
        jb_all = jb_all[:, :, cols] * col_scale[None, None, :]
        r_all = data.r[a0:a1]
        if weight_theta is None:
            b_w, jc_w = b_all, jc_all
        else:
            b_w, _, jc_w = unit_vector_jacobians(data.x_px[a0:a1], data.y_px[a0:a1], weight_theta)
        for n in np.unique(chunk_counts[chunk_counts >= 3]):
            n = int(n)
            frames = f0 + np.flatnonzero(chunk_counts == n)
            i, j = independent_pairs(n)
            step = max(PAIR_BLOCK_ELEMENTS // (i.size * 2 * n), 1)
            for c in range(0, frames.size, step):
                rows = orders[starts[frames[c : c + step], None] + np.arange(n)] - a0  # (m, n) chunk rows, pair order
                pi, pj = rows[:, i].ravel(), rows[:, j].ravel()  # every frame's pairs as chunk rows
                m, p = rows.shape[0], i.size
                cov = pair_covariance(b_w[rows], jc_w[rows], i, j, 1.0)
                if form == "cos":
                    e = difference_residuals(b_all, r_all, pi, pj).reshape(m, p)
                    h_jac = difference_jacobian(b_all, jb_all, pi, pj).reshape(m, p, k)
                else:
                    e, h_jac, factor = _sine_terms(b_all, r_all, jb_all, pi, pj)
                    e, h_jac = e.reshape(m, p), h_jac.reshape(m, p, k)
                    if weight_theta is not None:
                        factor = _sine_terms(b_w, r_all, jb_all, pi, pj)[2]
                    factor = factor.reshape(m, p)
                    cov = cov * factor[:, :, None] * factor[:, None, :]
                # generalised least squares per frame, batched: X = P^-1 [H e], then H^T P^-1 H, H^T P^-1 e, e^T P^-1 e
                rhs = np.concatenate([h_jac, e[:, :, None]], axis=2)
                try:
                    x = np.linalg.solve(cov, rhs)
                except np.linalg.LinAlgError:
                    x = np.stack([_solve_or_zero(cv, rh) for cv, rh in zip(cov, rhs, strict=True)])
                normal += np.einsum("mpk,mpl->kl", h_jac, x[:, :, :k])
                grad += np.einsum("mpk,mp->k", h_jac, x[:, :, k])
                cost += float(np.einsum("mp,mp->", e, x[:, :, k]))
                n_pairs += e.size
    return normal, grad, cost, n_pairs


def _solve_or_zero(cov: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """P^-1 rhs for one frame, or zero (no information) for a singular frame geometry (collinear stars)."""
    try:
        return np.linalg.solve(cov, rhs)
    except np.linalg.LinAlgError:
        return np.zeros_like(rhs)


def fit_interstar(
    data: CalibrationData,
    theta0: np.ndarray,
    params: CameraParams,
    estimate: tuple[str, ...],
    form: str,
    orders: np.ndarray,
    levenberg_marquardt: bool = False,
    max_iter: int = 30,
    frame_mask: np.ndarray | None = None,
    history: list[dict] | None = None,
    label: str = "",
    progress: Callable[[dict], None] | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Minimise the whitened interstar cost over ``estimate`` from ``theta0``.

    Gauss-Newton (seed 000 eq. 13, iterated) or, with ``levenberg_marquardt``, Marquardt-damped steps accepted only
    when the cost decreases (seed 004 sec. 2.1 and 2.3, after More 1978). Returns (theta, N, cost, n_pairs) with N
    the normal matrix at the solution in model-vector units.
    """
    cols = parameter_columns(estimate)
    scale = parameter_scales(params)[cols]
    theta = theta0.copy()
    damping = START_DAMPING if levenberg_marquardt else 0.0
    normal, grad, cost, n_pairs = interstar_normals(data, theta, cols, form, orders, scale, frame_mask)
    for _it in range(max_iter):
        accepted = False
        for _trial in range(MAX_DAMPING_TRIALS if levenberg_marquardt else 1):
            damped = normal + damping * np.diag(np.diag(normal))
            dx = solve_scaled(damped, grad)
            trial = theta.copy()
            trial[cols] += dx * scale
            # judge the step with the weights of the current iterate (IRLS; see interstar_normals)
            c_trial = interstar_normals(data, trial, cols, form, orders, scale, frame_mask, weight_theta=theta)[2]
            if not levenberg_marquardt or (np.isfinite(c_trial) and c_trial <= cost):
                accepted = True
                break
            damping = max(DAMPING_GROWTH * damping, INITIAL_DAMPING)
        if not accepted:
            break
        step_sigmas = float(np.sqrt(max(dx @ grad, 0.0)))
        decrease = (cost - c_trial) / max(cost, 1e-300)
        # reweight at the accepted point: the next step starts from its own normal equations and cost
        n_new, g_new, c_new, p_new = interstar_normals(data, trial, cols, form, orders, scale, frame_mask)
        theta, normal, grad, cost, n_pairs = trial, n_new, g_new, c_new, p_new
        if levenberg_marquardt:
            damping = damping / DAMPING_GROWTH if damping > DAMPING_FLOOR else 0.0
        entry = {
            "iteration": len(history or []) + 1,
            "stage": label,
            "cost": cost,
            "step_sigmas": step_sigmas,
            "n_pairs": n_pairs,
        }
        if history is not None:
            history.append(entry)
        if progress:
            progress(entry)
        if step_sigmas < STEP_TOL_UNIT_NOISE or abs(decrease) < COST_ROUNDING:
            break
    unscale = 1.0 / scale
    return theta, normal * unscale[:, None] * unscale[None, :], cost, n_pairs


def central_frame_subset(data: CalibrationData, params: CameraParams, fraction: float = CENTRAL_FRACTION):
    """Stars within ``fraction`` of the half-diagonal from the detector centre, frames with >= 3 of them."""
    w, h = params.image_size_px
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    radius = fraction * 0.5 * float(np.hypot(w, h))
    central = np.hypot(data.x_px - cx, data.y_px - cy) <= radius
    return data.select(central)[0]


def calibrate_interstar(
    data: CalibrationData,
    nominal: CameraParams,
    form: str,
    improved: bool,
    estimate: tuple[str, ...] = ESTIMATE_NAMES,
    rounds: int = IMPROVED_ROUNDS,
    progress: Callable[[dict], None] | None = None,
) -> InterstarFit:
    """Seed 000's methods: ``form`` 'cos' or 'sin'; ``improved`` selects the two-step iteration of sec. 2.

    ``estimate`` restricts the parameters (the plain methods estimate only its optical part). The improved method
    has reached its fixed point when a Gauss-Newton step of the joint problem from where it stands is below
    :data:`ALTERNATION_CONVERGED_SIGMAS`; when the paper's rounds leave it farther, it continues with joint steps
    (:func:`_improved`), and a fit that still does not settle says which parameters its angles cannot separate."""
    if form not in ("cos", "sin"):
        raise ValueError(f"unknown interstar form {form!r}")
    optical = tuple(n for n in OPTICAL if n in estimate)
    distortion = tuple(n for n in DISTORTION if n in estimate)
    fit = _Fitter(data, nominal, form, frame_pair_orders(data), [], [], progress)
    if not improved:
        if not optical:
            raise ValueError("the plain interstar methods estimate f, x0, y0: none of them selected")
        theta = fit.run(nominal.model_vector(np.float64), optical, "optical", data)
        fit.stages.append({"name": "optical", "theta": theta.copy()})
        final = optical
    else:
        theta = _improved(fit, optical, distortion, rounds)
        final = optical + distortion
    cols = parameter_columns(final)
    # the covariance of the (alternation's) fixed point is that of the joint problem: evaluated there
    normal, grad, cost, n_pairs = interstar_normals(data, theta, cols, form, fit.orders, np.ones(cols.size))
    sigma_px = float(np.sqrt(cost / max(n_pairs - len(final), 1)))
    remainder = newton_step_sigmas(normal, grad, sigma_px) if improved else 0.0
    converged = remainder < ALTERNATION_CONVERGED_SIGMAS
    return InterstarFit(
        theta=theta,
        estimate=tuple(n for n in ESTIMATE_NAMES if n in final),
        normal=normal,
        sigma_estimated_px=sigma_px,
        history=fit.history,
        stages=fit.stages,
        last_round_step_sigmas=remainder,
        converged=converged,
        failure=None if converged else _unsettled_message(form, final, normal, remainder, rounds),
    )


@dataclass
class _Fitter:
    """What every stage of a seed-000 fit shares: the data, the nominal, the form, the pair orders, the records."""

    data: CalibrationData
    nominal: CameraParams
    form: str
    orders: np.ndarray
    history: list[dict]
    stages: list[dict]
    progress: Callable[[dict], None] | None

    def run(self, theta: np.ndarray, names: tuple[str, ...], label: str, data: CalibrationData | None = None):
        """:func:`fit_interstar` over ``names`` from ``theta`` (on ``data``, default all; its pair orders)."""
        source = self.data if data is None else data
        orders = self.orders if source is self.data else frame_pair_orders(source)
        return fit_interstar(
            source,
            theta,
            self.nominal,
            names,
            self.form,
            orders,
            history=self.history,
            label=label,
            progress=self.progress,
        )[0]


def _improved(fit: _Fitter, optical: tuple[str, ...], distortion: tuple[str, ...], rounds: int) -> np.ndarray:
    """Seed 000 sec. 2: (1) the estimated distortion coefficients 0, (x0, y0, f) from the central field; (2) the
    distortion with the optical part held, (3) the optical part with the distortion held, ``rounds`` times. Where the
    two blocks trade off strongly (f with k1; x0, y0 with p1, p2) this block coordinate descent contracts only by the
    squared canonical correlation per round (~0.99 seen: docs/calibration.md), so after its rounds, if a joint
    Gauss-Newton step from there is above :data:`ALTERNATION_CONVERGED_SIGMAS`, the same cost is minimised over
    both blocks at once from there: the fixed point of the alternation is the joint problem's stationary point,
    which those steps reach (recorded as the stage ``joint``)."""
    data, nominal = fit.data, fit.nominal
    theta = nominal.model_vector(np.float64)
    theta[[ESTIMATE_NAMES.index(n) for n in distortion]] = 0.0  # step 1; parameters held keep the nominal
    if optical:
        central = central_frame_subset(data, nominal)
        source = central if central.n_frames else data
        theta = fit.run(theta, optical, "optical (central field)", source)
        fit.stages.append({"name": "optical (central field)", "theta": theta.copy()})
    for k in range(rounds):
        if distortion:
            theta = fit.run(theta, distortion, f"distortion {k + 1}")
        if optical:
            theta = fit.run(theta, optical, f"optical {k + 1}")
        fit.stages.append({"name": f"round {k + 1}", "theta": theta.copy()})
    final = optical + distortion
    if optical and distortion and _remainder_sigmas(fit, theta, final) >= ALTERNATION_CONVERGED_SIGMAS:
        theta = fit.run(theta, final, "joint")
        fit.stages.append({"name": "joint", "theta": theta.copy()})
    return theta


def _remainder_sigmas(fit: _Fitter, theta: np.ndarray, names: tuple[str, ...]) -> float:
    """The joint Gauss-Newton step from ``theta`` in standard deviations (:func:`newton_step_sigmas`)."""
    cols = parameter_columns(names)
    normal, grad, cost, n_pairs = interstar_normals(fit.data, theta, cols, fit.form, fit.orders, np.ones(cols.size))
    return newton_step_sigmas(normal, grad, float(np.sqrt(cost / max(n_pairs - cols.size, 1))))


def newton_step_sigmas(normal: np.ndarray, grad: np.ndarray, sigma_px: float) -> float:
    """How far the minimum of the quadratic model lies, in standard deviations of the estimate: the Gauss-Newton
    step dx = N^-1 g in the metric of N, sqrt(dx^T N dx) / sigma (N and g for unit centroid noise)."""
    dx = solve_scaled(normal, grad)
    return float(np.sqrt(max(dx @ grad, 0.0))) / max(sigma_px, 1e-300)


def _unsettled_message(form: str, names: tuple[str, ...], normal: np.ndarray, remainder: float, rounds: int) -> str:
    """Why the improved method did not settle: how far it stands from the joint minimum and the most correlated
    pair of an optical and a distortion parameter (what the interstar angles of this session cannot separate)."""
    cov = covariance_from_normal(normal, 1.0)
    d = np.sqrt(np.abs(np.diag(cov)))
    corr = cov / np.outer(np.where(d > 0, d, 1.0), np.where(d > 0, d, 1.0))
    pairs = [(abs(corr[i, j]), a, b, corr[i, j]) for i, a in enumerate(names) for j, b in enumerate(names)]
    pairs = [p for p in pairs if p[1] in OPTICAL and p[2] in DISTORTION and np.isfinite(p[0])]
    worst = max(pairs, default=None)
    what = (
        f"its interstar angles cannot separate {worst[1]} from {worst[2]} (correlation {worst[3]:+.4f})"
        if worst is not None
        else "its interstar angles do not determine the estimated parameters"
    )
    name = {"cos": "cosine", "sin": "sine"}[form]
    return (
        f"seed 000's improved {name} method did not settle: after {rounds} rounds and a joint refinement it stands "
        f"{remainder:.3g} sigma from the minimum of its own cost; {what}. Estimate fewer parameters (--estimate) or "
        "use the bundle method"
    )
