"""Onboard recursive camera calibration from interstar angles (docs/architecture.md: onboard; the sensor's estimator).

The lineage is Samaan, Griffith and Junkins (2001) and Griffith, Singla and Junkins (2002) (seed README; seed 004
sec. 1 describes them as a Kalman filter on the interstar cosines whose state and covariance are updated frame by
frame and whose star data are then discarded). This implementation keeps their idea, the attitude-free interstar
measurement b_i . b_j = r_i . r_j (seed 004 eq. 1, seed 000 eq. 3), and makes it fit float32:

* Measurement: the difference form e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 (:mod:`onboard.interstar`) over the
  frame's 2n - 3 independent pairs, whitened with the Cholesky factor of their covariance from the centroid noise.
  The plain cosine b_i . b_j ~ 1 keeps only |log2(1 - cos)| fewer bits (see ``tests/test_recursive_precision.py``).
* State: a subset of (f, x0, y0, k1, k2, k3, p1, p2, s1, s2) held as a scaled deviation from the nominal,
  theta = theta_nom + s * x, s = the prior 1-sigma, so every state is O(1) and float32's range is never strained.
  x is kept as an unevaluated sum x_hi + x_lo (compensated summation) because the per-frame increments near
  convergence are below float32's resolution of x ~ 1, and the model is evaluated at fl(theta_nom + s x_hi) with the
  rounding of theta corrected to first order in the innovation, so F's float32 grid (5e-4 px at F = 6000 px) does
  not bias the estimate.
* Update: Bierman U-D scalar updates (:mod:`onboard.ud`), one per whitened pair, iterated (IEKF) while a frame moves
  the state far enough for the linearisation to matter (cold start), at most ``max_iterations`` times.
* Gating: a per-pair chi-square test on the predicted innovation variance h P h + R_pp; a star whose two pairs to the
  base stars both fail (or a base star whose pairs mostly fail) is a misidentification and is removed.
* Burn-in: during the first ``burn_in_frames`` the covariance is divided by ((k - 1) / k)^power each frame, so the
  first frames, linearised far from the truth, fade out; without it their second-order error biases the weakly
  observable combination of principal point, decentering and thin prism (a principal-point shift equals a rotation plus
  p1 = -s1 = dx0 / 2F^2 to first order). Frames linearised at a point off along that combination also get a wrong
  Jacobian column for it, to first order, so the filter's error exceeds the batch ML's by a random (not a biased)
  amount of 0.6 CRB with a 200-frame linear burn-in, 0.4-0.5 CRB with the default 300 frames squared, for x and y
  alike (``benchmarks/recursive_crb_study.py``). Cost: 4-12 % on the final sigma.
* Process noise: a random walk per parameter (``process_noise``), and a focal-length drift detector: each frame's
  focal score g = h_f . nu (whitened innovations against the focal column) has zero mean for a static camera and
  known variance h_f . S h_f; when sum(g) / sqrt(sum var) over W frames exceeds ``drift_threshold`` the focal random
  walk ``drift_focal_mm_per_frame`` is switched on, so thermal drift is tracked while a static camera keeps the
  full-memory (Cramer-Rao) estimate.

* Fixed point: ``update(..., front_end=onboard.fixedpoint.FixedFrame(...))`` takes the residuals from the integer
  front end (Q30 unit vectors, Q61 residuals; ``hostlink replay --precision fixed``) for a sensor without an FPU.
  The filter (Jacobians, pair covariance, U-D updates) stays in float32, by a soft-float library on such a sensor:
  its O(P K^2) work per frame is the same as here, while the front end holds the precision that matters.

Arithmetic order: every float32 sum of the filter (residual corrections, gating, Cholesky whitening, forward
substitution, focal score, drift statistic) is written in the order :mod:`onboard.linalg32` states, not with numpy's
matmul/linalg/sum, so a port that keeps that order (onboard/c) reproduces the state bit for bit (docs/port-kit.md).

Work per frame is bounded (stars are capped at ``max_stars`` = N, pairs P = 2N - 3, states K <= 10):
camera Jacobians O(30 N), pair covariance O(P N), Cholesky O(P^3 / 3), whitening O(P^2 (K + 1)),
updates O(6 P K^2); at most ``max_iterations`` linearisations and 2 misidentification passes, i.e. at most
``(max_iterations + 2) * (P^3/3 + P^2 (K + 1) + 6 P K^2 + 40 N K)`` flops, about 1.0 Mflop for N = 32, K = 10.
Buffers of the state are sized at :func:`create`; numpy temporaries inside a frame are bounded by N, P and K
(stack buffers in a C port).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from onboard.camera import unit_vector_jacobians
from onboard.interstar import (
    difference_jacobian,
    difference_residuals,
    independent_pairs,
    order_for_pairs,
    pair_covariance,
)
from onboard.linalg32 import cholesky_lower, dot, forward_solve, matmul, matvec, sum_seq, vecmat
from onboard.params import ESTIMATE_NAMES, N_PARAMS, CameraParams
from onboard.ud import BiermanWork, agee_turner_update, bierman_update, bierman_work, ud_covariance

_STATE_MAGIC = 0x52435331  # "RCS1"
_STATE_VERSION = 1
#: relative inflation of each pair's variance (see :func:`_linearise`); the same in float32 and float64.
_R_JITTER = 1e-4


@dataclass(frozen=True)
class RecursiveConfig:
    """Tuning of the recursive estimator. Parameter-unit vectors are in ESTIMATE_NAMES order (f in mm)."""

    #: stars used per frame at most (the first ``max_stars`` identified ones); fixes every buffer size.
    max_stars: int = 32
    #: 1-sigma centroid noise per axis [px]; sets the pair covariance R.
    centroid_noise_px: float = 0.05
    #: prior 1-sigma per parameter (parameter units); None = cold-start defaults (:func:`default_prior_sigma`).
    prior_sigma: tuple[float, ...] | None = None
    #: random-walk 1-sigma per frame per parameter (parameter units; f in mm); zeros = a static camera.
    process_noise: tuple[float, ...] = (0.0,) * N_PARAMS
    #: per-pair gate in sigmas of the predicted innovation (5 sigma: a false rejection per 1.7 million pairs).
    pair_gate_sigma: float = 5.0
    #: linearisations per frame at most (iterated update); 1 = a plain extended filter.
    max_iterations: int = 4
    #: relinearise when a frame moved any scaled state by more than this (prior sigmas); cold start only.
    iteration_tol: float = 1e-2
    #: frames whose pairs mostly fail in a row before the covariance is reopened to the prior (divergence guard).
    reopen_after_frames: int = 5
    #: burn-in forgetting: for frames k <= burn_in_frames the covariance is divided by ((k - 1) / k)^burn_in_power,
    #: which weights frame j by (j / burn_in_frames)^power at the end of the burn-in, fading out the first frames,
    #: linearised far from the truth (their second-order error otherwise biases the weakly observable principal
    #: point / decentering / thin-prism combination). 0 frames = a plain full-memory filter.
    #: 300 frames, power 2 (benchmarks/recursive_crb_study.py, 24 seed-004 sessions of 1000 frames): the filter's
    #: excess over the batch ML estimate, RMS (rec - ML) / CRB, is 0.39-0.51 for every parameter (200 frames, power 1:
    #: 0.56-0.64 on the principal point / decentering / prism, 0.29-0.33 on f, k); the reported sigma costs 4-12 %.
    burn_in_frames: int = 300
    burn_in_power: float = 2.0
    #: focal-length drift detection (needs f in the state).
    drift_detect: bool = True
    drift_window_frames: int = 200
    drift_start_frames: int = 400
    drift_threshold: float = 4.5
    #: focal random walk switched on by the detector, 1-sigma per frame [mm] (0.07 um): the built-in 70 mm lens's;
    #: another lens's is :func:`drift_focal_mm_per_frame_for` its focal length (thermal drift scales with it).
    drift_focal_mm_per_frame: float = 7e-5


#: The focal length the default ``drift_focal_mm_per_frame`` was tuned on: the built-in camera's (seed 004, 70 mm).
DRIFT_WALK_DESIGN_FOCAL_MM = 70.0


def drift_focal_mm_per_frame_for(focal_length_mm: float) -> float:
    """The focal random walk (1-sigma per frame [mm]) for a lens of ``focal_length_mm``: the default's relative rate
    (7e-5 mm / 70 mm = 1e-6 of f per frame) times f. A lens's thermal focal change is CTE x f x dT, proportional to f
    at the same temperature swing, so the walk the default allows the 70 mm lens is the same fraction of any other
    (70 mm gives the default exactly)."""
    return RecursiveConfig.drift_focal_mm_per_frame * (focal_length_mm / DRIFT_WALK_DESIGN_FOCAL_MM)


@dataclass
class FrameResult:
    """What one frame did: stars in/used, misidentified stars (indices into the frame's input rows), pairs used and
    rejected, linearisations, mean normalised innovation squared of the used pairs (1 when the model fits)."""

    n_stars: int = 0
    n_used: int = 0
    rejected_stars: tuple[int, ...] = ()
    n_pairs: int = 0
    n_pairs_rejected: int = 0
    iterations: int = 0
    nis: float = float("nan")
    focal_score: float = 0.0
    focal_score_var: float = 0.0
    skipped: str = ""


@dataclass
class RecursiveState:
    """Everything the estimator keeps between frames (sized at :func:`create`, never reallocated)."""

    nominal: CameraParams
    config: RecursiveConfig
    dtype: np.dtype
    idx: np.ndarray  # (K,) int32 model-vector slots of the estimated parameters, ascending (f first)
    theta_nom: np.ndarray  # (10,) model vector (F in px) of the nominal
    scale: np.ndarray  # (10,) model units per state unit (prior sigma); meaningful at idx
    x_hi: np.ndarray  # (K,) scaled deviation, compensated pair x_hi + x_lo
    x_lo: np.ndarray
    u: np.ndarray  # (K, K) unit upper triangular
    d: np.ndarray  # (K,)
    q: np.ndarray  # (K,) process noise variance per frame [scaled^2]
    q_drift: float  # focal random-walk variance [scaled^2] added when drift is detected
    d_prior: np.ndarray  # (K,) prior variances [scaled^2] (all ones by construction of the scale)
    frames: int = 0
    updates: int = 0
    inconsistent_run: int = 0
    drift_on: bool = False
    drift_frame: int = -1
    nis_sum: float = 0.0
    nis_count: int = 0
    ring_pos: int = 0
    ring_count: int = 0
    ring_g: np.ndarray = field(default=None)  # (W,) per-frame focal score h_f . nu (whitened)
    ring_v: np.ndarray = field(default=None)  # (W,) its predicted variance h_f . S h_f
    # scratch (not part of the saved state)
    work: BiermanWork = field(default=None, repr=False)
    u0: np.ndarray = field(default=None, repr=False)
    d0: np.ndarray = field(default=None, repr=False)
    xi: np.ndarray = field(default=None, repr=False)
    theta_r: np.ndarray = field(default=None, repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(ESTIMATE_NAMES[k] for k in self.idx)


def default_prior_sigma(nominal: CameraParams, distortion_px: float = 5.0) -> np.ndarray:
    """Cold-start prior 1-sigma per parameter (parameter units): 3 % of f, 5 % of the larger image side for the
    principal point, and for each distortion term the coefficient that moves the detector corner (radius r_max,
    half the diagonal) by ``distortion_px``: k1 D / r^3, k2 D / r^5, k3 D / r^7, p1 p2 s1 s2 D / r^2."""
    w, h = nominal.image_size_px
    r = 0.5 * float(np.hypot(w, h))
    dpx = float(distortion_px)
    return np.array(
        [
            0.03 * nominal.focal_length_mm,
            0.05 * max(w, h),
            0.05 * max(w, h),
            dpx / r**3,
            dpx / r**5,
            dpx / r**7,
            dpx / r**2,
            dpx / r**2,
            dpx / r**2,
            dpx / r**2,
        ]
    )


def update_cost_flops(n_stars: int, n_states: int, config: RecursiveConfig | None = None) -> int:
    """Worst-case floating-point operations of one :func:`update` with ``n_stars`` stars (capped at
    ``config.max_stars``) and ``n_states`` estimated parameters: the bound of the module docstring,
    ``(max_iterations + 2) * (P^3/3 + P^2 (K + 1) + 6 P K^2 + 40 N K)`` with P = 2N - 3 independent pairs (about
    1.0 Mflop for N = 32, K = 10). A sensor budgets its estimator with it (``onboard.firmware.EstimatorBudget``)."""
    cfg = config or RecursiveConfig()
    n = min(max(int(n_stars), 0), cfg.max_stars)
    if n < 3:
        return 0
    p, k = 2 * n - 3, int(n_states)
    per_linearisation = p**3 // 3 + p * p * (k + 1) + 6 * p * k * k + 40 * n * k
    return (cfg.max_iterations + 2) * per_linearisation


def parse_estimate_names(text: str | None) -> tuple[str, ...]:
    """``"f,x0,y0"`` -> ("f", "x0", "y0") in ESTIMATE_NAMES order; None/"" -> all. Raises ValueError naming the
    unknown or repeated name."""
    if text is None or text.strip() == "" or text.strip() == "all":
        return ESTIMATE_NAMES
    names = [s.strip() for s in text.split(",")]
    for n in names:
        if n not in ESTIMATE_NAMES:
            raise ValueError(f"unknown parameter {n!r} (allowed: {','.join(ESTIMATE_NAMES)})")
    if len(set(names)) != len(names):
        raise ValueError("a parameter is named twice")
    return tuple(n for n in ESTIMATE_NAMES if n in names)


def _to_model_units(values: np.ndarray, pitch_um: float) -> np.ndarray:
    """Parameter units (f mm) -> model units (F px) for a sigma-like vector."""
    out = np.array(values, dtype=np.float64)
    out[0] = out[0] * 1000.0 / pitch_um
    return out


def create(
    nominal: CameraParams,
    estimate: tuple[str, ...] = ESTIMATE_NAMES,
    config: RecursiveConfig | None = None,
    dtype: type | np.dtype = np.float32,
) -> RecursiveState:
    """A fresh estimator at the nominal with covariance = prior (all buffers allocated here, once)."""
    config = config or RecursiveConfig()
    dt = np.dtype(dtype)
    if dt not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"dtype must be float32 or float64, got {dt}")
    if not estimate:
        raise ValueError("no parameter to estimate")
    if config.max_stars < 3:
        raise ValueError("max_stars must be >= 3")
    idx = np.array(sorted(ESTIMATE_NAMES.index(n) for n in estimate), dtype=np.int32)
    k = idx.size
    sigma = np.asarray(config.prior_sigma if config.prior_sigma is not None else default_prior_sigma(nominal))
    if sigma.shape != (N_PARAMS,) or not np.all(np.isfinite(sigma)) or np.any(sigma[idx] <= 0):
        raise ValueError("prior_sigma must hold 10 finite values, positive for every estimated parameter")
    pn = np.asarray(config.process_noise, dtype=np.float64)
    if pn.shape != (N_PARAMS,) or np.any(~np.isfinite(pn)) or np.any(pn < 0):
        raise ValueError("process_noise must hold 10 finite values >= 0")
    scale = _to_model_units(sigma, nominal.pixel_pitch_um)
    scale[scale <= 0] = 1.0
    q = (_to_model_units(pn, nominal.pixel_pitch_um)[idx] / scale[idx]) ** 2
    q_drift = (config.drift_focal_mm_per_frame * 1000.0 / nominal.pixel_pitch_um / scale[0]) ** 2
    w = max(1, int(config.drift_window_frames))
    return RecursiveState(
        nominal=nominal,
        config=config,
        dtype=dt,
        idx=idx,
        theta_nom=nominal.model_vector(dt),
        scale=scale.astype(dt),
        x_hi=np.zeros(k, dt),
        x_lo=np.zeros(k, dt),
        u=np.eye(k, dtype=dt),
        d=np.ones(k, dt),
        q=q.astype(dt),
        q_drift=float(q_drift),
        d_prior=np.ones(k, dt),
        ring_g=np.zeros(w, dt),
        ring_v=np.zeros(w, dt),
        work=bierman_work(k, dt),
        u0=np.eye(k, dtype=dt),
        d0=np.ones(k, dt),
        xi=np.zeros(k, dt),
        theta_r=np.zeros(N_PARAMS, dt),
    )


# ---------------------------------------------------------------------------------------------------------------
# the model at the current state


def _two_sum(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """s = fl(a + b) and the exact rounding error (Knuth's TwoSum), elementwise, in the inputs' dtype."""
    s = a + b
    bb = s - a
    err = (a - (s - bb)) + (b - bb)
    return s, err


def _linearisation_point(state: RecursiveState, x_hi: np.ndarray, x_lo: np.ndarray) -> np.ndarray:
    """Fill ``state.theta_r`` = fl(theta_nom + s x_hi) and return the rounding left out, in state units:
    delta = (theta_nom + s (x_hi + x_lo) - theta_r) / s, so that e(theta) = e(theta_r) - H delta to first order."""
    step = np.zeros(N_PARAMS, state.dtype)
    step[state.idx] = state.scale[state.idx] * x_hi
    theta_r, err = _two_sum(state.theta_nom, step)
    state.theta_r[:] = theta_r
    return err[state.idx] / state.scale[state.idx] + x_lo


@dataclass
class _Linearised:
    e: np.ndarray  # (P,) residuals at the state (compensated)
    h: np.ndarray  # (P, K) d prediction / d state
    r: np.ndarray  # (P, P) pair covariance, normalised by r_norm
    r_norm: float
    pi: np.ndarray
    pj: np.ndarray


def _linearise(state: RecursiveState, xs, ys, rs, x_hi, x_lo, front=None, order=None) -> _Linearised:
    """Residuals, Jacobian (state units) and pair covariance of the independent pairs of ordered stars.

    ``front`` (see :func:`update`'s ``front_end``) replaces the residuals by the fixed-point front end's, evaluated
    at theta_r on its grids (theta_q): that rounding joins ``delta``; H and R stay those of this dtype."""
    delta = _linearisation_point(state, x_hi, x_lo)
    b, jb_theta, jb_centroid = unit_vector_jacobians(xs, ys, state.theta_r)
    jb = jb_theta[:, :, state.idx] * state.scale[state.idx]
    pi, pj = independent_pairs(xs.shape[0])
    if front is None:
        e = difference_residuals(b, rs, pi, pj)
    else:
        e, theta_q = front(state.theta_r, order, pi, pj)
        rounding = (state.theta_r.astype(np.float64) - theta_q)[state.idx] / state.scale[state.idx]
        delta = delta + rounding.astype(state.dtype)
    h = difference_jacobian(b, jb, pi, pj)
    e = e - matvec(h, delta)
    r = pair_covariance(b, jb_centroid, pi, pj, state.config.centroid_noise_px)
    r_norm = float(sum_seq(np.diag(r)) / state.dtype.type(r.shape[0]))  # the mean, summed in order
    if not r_norm > 0:
        r_norm = 1.0
    # A star nearly on the line through the base pair makes its two pairs nearly dependent (the pair framework
    # loses infinitesimal rigidity) and R nearly singular: float32 Cholesky then fails. Inflating each pair's own
    # variance by _R_JITTER (0.01 %) bounds the condition number by ~1 / _R_JITTER at a negligible information cost.
    r[np.diag_indices_from(r)] *= state.dtype.type(1.0 + _R_JITTER)
    return _Linearised(e=e, h=h, r=r / state.dtype.type(r_norm), r_norm=r_norm, pi=pi, pj=pj)


def _pair_chi2(state: RecursiveState, lin: _Linearised) -> np.ndarray:
    """e_p^2 / (h_p P h_p + R_pp), normalised units, with P = U D U^T of the state."""
    g = matmul(lin.h, state.u)
    s = matvec(g * g, state.d) + np.diag(lin.r) * state.dtype.type(lin.r_norm)
    return lin.e * lin.e / s


def _misidentified(fail: np.ndarray, n: int) -> np.ndarray:
    """Stars whose pairs are inconsistent, from the failing independent pairs (order (0,1), (0,k)..., (1,k)...):
    star k >= 2 when both its pairs fail; a base star when (0,1) fails and more than half its other pairs fail."""
    bad = np.zeros(n, dtype=bool)
    f0k = fail[1 : n - 1]
    f1k = fail[n - 1 :]
    bad[2:] = f0k & f1k
    if fail[0]:
        bad[0] = np.mean(f0k) > 0.5 if n > 2 else False
        bad[1] = np.mean(f1k) > 0.5 if n > 2 else False
    return bad


# ---------------------------------------------------------------------------------------------------------------
# the per-frame step


def time_update(state: RecursiveState) -> None:
    """Process noise for one frame: U D U^T += diag(q) by Agee-Turner rank-one updates (O(K^2) each)."""
    k = state.frames
    cfg = state.config
    if 2 <= k <= cfg.burn_in_frames and cfg.burn_in_power > 0:
        state.d *= state.dtype.type((k / (k - 1)) ** cfg.burn_in_power)
    q = state.q.astype(np.float64)
    if state.drift_on and state.idx[0] == 0:
        q[0] += state.q_drift
    a = np.zeros(state.idx.size, state.dtype)
    for k in np.flatnonzero(q):
        a[:] = 0
        a[k] = 1
        agee_turner_update(state.u, state.d, a, state.dtype.type(q[k]))


def update(
    state: RecursiveState,
    x_px: np.ndarray,
    y_px: np.ndarray,
    r_ref: np.ndarray,
    identified: np.ndarray | None = None,
    front_end=None,
) -> FrameResult:
    """Process one frame: centroids (x_px, y_px) [px], reference unit vectors r_ref (N, 3) of the identified stars
    (rows of unidentified stars are ignored: ``identified`` False or a non-finite r). Updates ``state`` in place.

    ``front_end`` (optional, e.g. :class:`onboard.fixedpoint.FixedFrame` of the same frame's rows) computes the
    interstar residuals instead of this dtype's camera model: ``front_end.residuals(theta, rows, pi, pj)`` returns
    (e in theta's dtype, the float64 model vector it evaluated) for the input rows ``rows`` in pair order. The
    Jacobians, the pair covariance and the U-D update stay in the state's dtype (float32 on a sensor without an FPU,
    by a soft-float library: O(P K^2) per frame against the front end's per-star work). Without it nothing changes.

    Steps: time update; gate the independent pairs at the prior and remove misidentified stars (at most two
    passes); iterated U-D update; post-fit editing (a star whose pairs the updated state still cannot explain is
    removed and the frame redone from the prior, once): the prior gate is wide during a cold start."""
    dt = state.dtype
    x_px = np.asarray(x_px)
    y_px = np.asarray(y_px)
    r_ref = np.asarray(r_ref)
    ok = np.isfinite(x_px) & np.isfinite(y_px) & np.all(np.isfinite(r_ref), axis=1)
    if identified is not None:
        ok &= np.asarray(identified, dtype=bool)
    sel = _distinct_stars(np.flatnonzero(ok), x_px, y_px, dt)[: state.config.max_stars]
    result = FrameResult(n_stars=int(x_px.shape[0]))
    state.frames += 1
    time_update(state)
    if sel.size < 3:
        result.skipped = "fewer than 3 identified stars"
        _record_history(state)
        return result
    xs_all = x_px[sel].astype(dt)
    ys_all = y_px[sel].astype(dt)
    rs_all = r_ref[sel].astype(dt)
    keep = np.ones(sel.size, dtype=bool)
    front = None
    if front_end is not None:

        def front(theta, order, pi, pj):
            return front_end.residuals(theta, sel[order], pi, pj)

    state.u0[:] = state.u
    state.d0[:] = state.d
    status = _process_with_editing(state, xs_all, ys_all, rs_all, keep, result, front)
    result.rejected_stars = tuple(int(sel[k]) for k in np.flatnonzero(~keep))
    if status:
        _skip_frame(state, result, status)
    else:
        _accept_frame(state, result)
    return result


def _process_with_editing(state: RecursiveState, xs_all, ys_all, rs_all, keep: np.ndarray, result, front) -> str:
    """The frame from the prior with post-fit editing: a star the updated state still cannot explain is removed from
    ``keep`` and the frame redone from the prior (state.u0, state.d0, x_hi + x_lo on entry), once. Returns the
    status ("" when the frame updated the state)."""
    prior_hi = state.x_hi.copy()
    prior_lo = state.x_lo.copy()
    status = ""
    for attempt in range(2):
        if attempt:
            state.u[:] = state.u0
            state.d[:] = state.d0
        status, post_bad = _process_frame(state, xs_all, ys_all, rs_all, keep, prior_hi, prior_lo, result, front)
        if status or not np.any(post_bad):
            break
        keep[post_bad] = False
    return status


def _skip_frame(state: RecursiveState, result: FrameResult, status: str) -> None:
    """A skipped frame: the prior's factors back; a run of inconsistent frames reopens the covariance."""
    state.u[:] = state.u0
    state.d[:] = state.d0
    result.skipped = status
    if status.startswith("most pairs"):
        state.inconsistent_run += 1
        if state.inconsistent_run >= state.config.reopen_after_frames:
            state.u[:] = np.eye(state.idx.size, dtype=state.dtype)
            state.d[:] = state.d_prior
            state.inconsistent_run = 0
            result.skipped += " (covariance reopened)"
    _record_history(state)


def _accept_frame(state: RecursiveState, result: FrameResult) -> None:
    """An updated frame: the counters, the NIS of single-iteration frames and the drift detector."""
    state.inconsistent_run = 0
    state.updates += 1
    if state.frames > state.config.drift_start_frames and result.iterations == 1:
        state.nis_sum += result.nis * result.n_pairs
        state.nis_count += result.n_pairs
    _record_history(state, result)
    _detect_drift(state)


def _distinct_stars(rows: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, dt: np.dtype) -> np.ndarray:
    """``rows`` without the stars whose centroid (in the estimator's dtype) repeats an earlier row's, order kept.

    A star reported twice adds a pair of zero length, whose predicted variance is zero: float64 Cholesky of the pair
    covariance fails and float32 whitens rounding noise with an enormous weight. It carries no information."""
    xy = np.stack([x_px[rows].astype(dt), y_px[rows].astype(dt)], axis=1)
    _, first = np.unique(xy, axis=0, return_index=True)
    return rows[np.sort(first)]


def _gate(state: RecursiveState, xs_all, ys_all, rs_all, keep: np.ndarray, front=None):
    """Gate at the prior, removing misidentified stars from ``keep`` (at most two passes). Returns
    (order, linearisation, failing pairs, status) with status "" when the frame can be used."""
    gate2 = state.config.pair_gate_sigma**2
    order = lin = fail = None
    for pass_ in range(3):
        live = np.flatnonzero(keep)
        if live.size < 3:
            return order, lin, fail, "fewer than 3 consistent stars"
        order = live[order_for_pairs(xs_all[live], ys_all[live])]
        lin = _linearise(state, xs_all[order], ys_all[order], rs_all[order], state.x_hi, state.x_lo, front, order)
        fail = _pair_chi2(state, lin) > gate2
        bad = _misidentified(fail, order.size)
        if not np.any(bad) or pass_ == 2 or np.count_nonzero(bad) > order.size // 2:
            break
        keep[order[bad]] = False
    if np.mean(fail) > 0.5:
        return order, lin, fail, "most pairs inconsistent with the state"
    return order, lin, fail, ""


def _process_frame(state, xs_all, ys_all, rs_all, keep, prior_hi, prior_lo, result, front=None):
    """One attempt at a frame from the prior (state.u0, state.d0, prior_hi + prior_lo): gate, iterated update,
    post-fit editing. Returns (status, post_bad): post_bad flags (as a mask over the frame's selected stars) stars the
    post-fit residuals reject."""
    post_bad = np.zeros(keep.size, dtype=bool)
    state.x_hi[:] = prior_hi
    state.x_lo[:] = prior_lo
    order, lin, fail, status = _gate(state, xs_all, ys_all, rs_all, keep, front)
    if status:
        return status, post_bad
    used = ~fail
    result.n_used = int(order.size)
    result.n_pairs = int(np.count_nonzero(used))
    result.n_pairs_rejected = int(np.count_nonzero(fail))
    stars = (xs_all[order], ys_all[order], rs_all[order])
    lin, step_state = _iterated_update(state, stars, order, lin, used, prior_hi, prior_lo, result, front)
    post_bad[order[_post_fit_bad(state, lin, step_state, order.size)]] = True
    return "", post_bad


def _iterated_update(state, stars, order, lin, used, prior_hi, prior_lo, result, front):
    """The iterated update of the gated frame (pairs ``used`` of the ordered ``stars``): relinearise from the
    prior's factors, whiten, Bierman, step, until the step is within iteration_tol or max_iterations. Leaves the
    estimate in x_hi + x_lo; returns the last linearisation and the last step (state units)."""
    cfg = state.config
    lin_hi, lin_lo = prior_hi.copy(), prior_lo.copy()
    step_state = np.zeros_like(prior_hi)
    nis = 0.0
    n_rows = 1
    for it in range(max(1, cfg.max_iterations)):
        if it > 0:
            state.u[:] = state.u0
            state.d[:] = state.d0
            lin = _linearise(state, *stars, lin_hi, lin_lo, front, order)
        white = _whiten(state, lin, used, (lin_hi - prior_hi) + (lin_lo - prior_lo))
        if it == 0:
            score, score_var = _focal_score(state, white)
        nis = _bierman_pass(state, white)
        n_rows = white.shape[0]
        new_hi, new_lo = _two_sum(prior_hi, state.xi + prior_lo)  # the new estimate, compensated
        step_state = (new_hi - lin_hi) + (new_lo - lin_lo)
        step = float(np.max(np.abs(step_state)))
        lin_hi, lin_lo = new_hi, new_lo
        result.iterations = it + 1
        if step <= cfg.iteration_tol:
            break
    state.x_hi[:] = lin_hi
    state.x_lo[:] = lin_lo
    result.nis = nis / max(1, n_rows)
    result.focal_score, result.focal_score_var = score, score_var
    return lin, step_state


def _whiten(state: RecursiveState, lin: _Linearised, used: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """The pseudo-measurement of xi = x - x_prior over the used pairs, y = e(x_lin) + H dx (dx = x_lin - x_prior),
    whitened: L^-1 [y s, H s] with R_used = L L^T and s = 1 / sqrt(r_norm), one row per pair."""
    h = lin.h[used]
    y = lin.e[used] + matvec(h, dx)
    chol = cholesky_lower(lin.r[np.ix_(used, used)])
    scale = state.dtype.type(1.0 / np.sqrt(lin.r_norm))
    return forward_solve(chol, np.column_stack([y * scale, h * scale]))


def _bierman_pass(state: RecursiveState, white: np.ndarray) -> float:
    """The whitened rows into the U-D factors by Bierman's update, state.xi from zero; returns the summed squared
    normalised innovations."""
    state.xi[:] = 0
    nis = 0.0
    for p in range(white.shape[0]):
        innov, s = bierman_update(state.u, state.d, state.xi, white[p, 1:], white[p, 0], state.work)
        nis += float(innov * innov / s)
    return nis


def _post_fit_bad(state: RecursiveState, lin: _Linearised, step_state: np.ndarray, n: int) -> np.ndarray:
    """Post-fit editing: every pair's residual (used or not) at the updated state, the linear prediction e - H step
    from the last point, gated again; the misidentified stars (mask over the n ordered stars) when they are at most
    half the frame, else none."""
    dt = state.dtype
    post = lin.e - matvec(lin.h, step_state)
    fail_post = post * post > state.config.pair_gate_sigma**2 * np.diag(lin.r) * dt.type(lin.r_norm)
    bad = _misidentified(fail_post, n)
    if np.count_nonzero(bad) > n // 2:
        bad[:] = False
    return bad


def _focal_score(state: RecursiveState, white: np.ndarray) -> tuple[float, float]:
    """Focal-length score of a frame at the prior: g = h_f . nu over the whitened pairs (nu the innovations, h_f
    the focal column) and its predicted variance h_f . (H P H^T + I) h_f. A static camera gives zero-mean scores; a
    focal error dF gives g ~ |h_f|^2 dF, so sum(g) / sqrt(sum(var)) over a window detects drift (0 if f is not
    estimated)."""
    if state.idx[0] != 0:
        return 0.0, 0.0
    hf = white[:, 1]
    g = float(dot(hf, white[:, 0]))
    a = vecmat(vecmat(hf, white[:, 1:]), state.u)  # U^T (H^T h_f)
    return g, float(dot(hf, hf) + dot(a * a, state.d))


def _record_history(state: RecursiveState, result: FrameResult | None = None) -> None:
    """Push the frame's focal score into the drift window (a skipped frame pushes zeros)."""
    w = state.ring_g.shape[0]
    g = result.focal_score if result is not None else 0.0
    v = result.focal_score_var if result is not None else 0.0
    state.ring_g[state.ring_pos] = g
    state.ring_v[state.ring_pos] = v
    state.ring_pos = (state.ring_pos + 1) % w
    state.ring_count = min(state.ring_count + 1, w)


def drift_statistic(state: RecursiveState) -> float:
    """sum(g) / sqrt(lambda sum(var)) over the last W frames' focal scores (:func:`_focal_score`): N(0, 1) for a
    static focal length, lambda being the mean normalised innovation squared (>= 1) so that an understated
    centroid noise does not raise alarms. NaN until W frames of history exist or when f is not estimated."""
    w = state.ring_g.shape[0]
    if state.idx[0] != 0 or state.ring_count < w:
        return float("nan")
    var = float(sum_seq(state.ring_v))
    lam = max(1.0, state.nis_sum / state.nis_count) if state.nis_count else 1.0
    if not var > 0:
        return float("nan")
    return float(sum_seq(state.ring_g)) / np.sqrt(lam * var)


def _detect_drift(state: RecursiveState) -> None:
    cfg = state.config
    if not cfg.drift_detect or state.drift_on or state.idx[0] != 0 or state.frames <= cfg.drift_start_frames:
        return
    z = drift_statistic(state)
    if np.isfinite(z) and abs(z) > cfg.drift_threshold:
        state.drift_on = True
        state.drift_frame = state.frames


# ---------------------------------------------------------------------------------------------------------------
# reading the state


def state_vector(state: RecursiveState) -> np.ndarray:
    """The estimated model vector theta = theta_nom + s (x_hi + x_lo), in float64 (F in px)."""
    theta = state.theta_nom.astype(np.float64)
    theta[state.idx] += state.scale[state.idx].astype(np.float64) * (
        state.x_hi.astype(np.float64) + state.x_lo.astype(np.float64)
    )
    return theta


def current_params(state: RecursiveState) -> CameraParams:
    """The current estimate as a camera parameter set (f in mm)."""
    return state.nominal.with_model_vector(state_vector(state))


def covariance(state: RecursiveState) -> np.ndarray:
    """Covariance (K, K) of the estimated parameters in model units (F in px), float64."""
    p = ud_covariance(state.u.astype(np.float64), state.d.astype(np.float64))
    s = state.scale[state.idx].astype(np.float64)
    return p * np.outer(s, s)


def sigma(state: RecursiveState) -> dict[str, float]:
    """1-sigma of each estimated parameter in parameter units (f in mm)."""
    sd = np.sqrt(np.diag(covariance(state)))
    out = {}
    for name, k, v in zip(state.names, state.idx, sd, strict=True):
        out[name] = float(v * state.nominal.pixel_pitch_um / 1000.0) if k == 0 else float(v)
    return out


# ---------------------------------------------------------------------------------------------------------------
# save / restore


def save_state(state: RecursiveState) -> bytes:
    """The estimator's state as bytes: an int64 header then the state's arrays in its dtype, little endian.

    Header: magic, version, itemsize, K, mask of estimated slots, frames, updates, drift_on, drift_frame, ring_pos,
    ring_count, W, nis_count, inconsistent_run. Data: theta_nom (10), scale (10), x_hi, x_lo, U (K*K), d, q,
    ring_g, ring_v (W each), nis_sum, q_drift."""
    mask = int(sum(1 << int(k) for k in state.idx))
    w = state.ring_g.shape[0]
    header = np.array(
        [
            _STATE_MAGIC,
            _STATE_VERSION,
            state.dtype.itemsize,
            state.idx.size,
            mask,
            state.frames,
            state.updates,
            int(state.drift_on),
            state.drift_frame,
            state.ring_pos,
            state.ring_count,
            w,
            state.nis_count,
            state.inconsistent_run,
        ],
        dtype="<i8",
    )
    data = np.concatenate(
        [
            state.theta_nom,
            state.scale,
            state.x_hi,
            state.x_lo,
            state.u.ravel(),
            state.d,
            state.q,
            state.ring_g,
            state.ring_v,
            np.array([state.nis_sum, state.q_drift], dtype=state.dtype),
        ]
    ).astype(state.dtype.newbyteorder("<"))
    return header.tobytes() + data.tobytes()


def restore_state(blob: bytes, nominal: CameraParams, config: RecursiveConfig | None = None) -> RecursiveState:
    """Rebuild a state saved by :func:`save_state` for the same nominal. Raises ValueError when the blob is not a
    state, has another version, size or dtype, or was saved against another nominal."""
    n_header = 14
    if len(blob) < 8 * n_header:
        raise ValueError("estimator state: too short")
    header = np.frombuffer(blob[: 8 * n_header], dtype="<i8")
    if int(header[0]) != _STATE_MAGIC:
        raise ValueError("estimator state: not a recursive-estimator state (bad magic)")
    if int(header[1]) != _STATE_VERSION:
        raise ValueError(f"estimator state: version {int(header[1])} not supported (expected {_STATE_VERSION})")
    itemsize, k, mask, w = int(header[2]), int(header[3]), int(header[4]), int(header[11])
    dtype = {4: np.dtype(np.float32), 8: np.dtype(np.float64)}.get(itemsize)
    if dtype is None:
        raise ValueError(f"estimator state: item size {itemsize} is neither float32 nor float64")
    names = tuple(n for b, n in enumerate(ESTIMATE_NAMES) if mask >> b & 1)
    if len(names) != k:
        raise ValueError("estimator state: parameter mask does not match the state size")
    config = config or RecursiveConfig()
    if w != max(1, int(config.drift_window_frames)):
        raise ValueError(f"estimator state: drift window {w} differs from the configuration")
    n_data = 2 * N_PARAMS + 2 * k + k * k + 2 * k + 2 * w + 2
    data_bytes = blob[8 * n_header :]
    if len(data_bytes) != n_data * itemsize:
        raise ValueError(f"estimator state: expected {n_data * itemsize} data bytes, found {len(data_bytes)}")
    data = np.frombuffer(data_bytes, dtype=dtype.newbyteorder("<")).astype(dtype)
    state = create(nominal, names, config, dtype)
    pos = 0

    def take(n: int) -> np.ndarray:
        nonlocal pos
        out = data[pos : pos + n]
        pos += n
        return out

    theta_nom = take(N_PARAMS)
    if not np.array_equal(theta_nom, state.theta_nom):
        raise ValueError("estimator state: saved against a different nominal parameter set")
    state.scale[:] = take(N_PARAMS)
    state.x_hi[:] = take(k)
    state.x_lo[:] = take(k)
    state.u[:] = take(k * k).reshape(k, k)
    state.d[:] = take(k)
    state.q[:] = take(k)
    state.ring_g[:] = take(w)
    state.ring_v[:] = take(w)
    tail = take(2)
    state.nis_sum = float(tail[0])
    state.q_drift = float(tail[1])
    state.frames, state.updates = int(header[5]), int(header[6])
    state.drift_on, state.drift_frame = bool(header[7]), int(header[8])
    state.ring_pos, state.ring_count = int(header[9]), int(header[10])
    state.nis_count, state.inconsistent_run = int(header[12]), int(header[13])
    if not (np.all(np.isfinite(state.x_hi)) and np.all(state.d > 0)):
        raise ValueError("estimator state: corrupt values (non-finite state or non-positive variance)")
    return state
