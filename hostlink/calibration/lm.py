"""The Levenberg-Marquardt loop of the bundle adjustment: one round at a fixed robust scale, with named
termination tests and the status it stops with (as scipy's ``optimize/_lsq/trf.py`` reports its ``status``).

The problem is the camera on the reduced cost sum_f min_C_f rho(e_f) (the attitudes eliminated in every pass,
:mod:`hostlink.calibration.passes`); each pass at a camera gives the Schur complement S and its right-hand side,
whose solution is the Gauss-Newton step (Marquardt's damping multiplies diag S by 1 + lambda, only after a step that
fails). An iteration:

1. solve the (damped) reduced normal equations for the step dx; its size in the camera's standard deviations is
   sqrt(dx^T S dx) / sigma;
2. termination tests that need no new pass: the step is below the tolerance (:attr:`Status.STEP_TOL`), or what
   the step leaves (the step times the contraction measured between undamped steps) is below the remainder
   tolerance (:attr:`Status.REMAINDER_TOL`); the step is applied either way;
3. a pass at the moved camera; the step is accepted when the cost does not rise beyond the rounding of its sum,
   else the damping grows (:data:`DAMPING_GROWTH`) and the step is solved again, at most :data:`MAX_DAMPING_TRIALS`
   times (:attr:`Status.NO_DESCENT`), unless the step was already negligible (:attr:`Status.SMALL_STEP`);
4. an accepted step whose relative decrease of the cost is below ``ftol`` ends the round (:attr:`Status.FTOL`);
   ``max_iter`` iterations over all rounds end it unconverged (:attr:`Status.MAX_ITER`).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.acceleration import ACCELERATION_MIN_SIGMAS
from hostlink.calibration.normal import solve_scaled
from hostlink.calibration.passes import PassSums, robust_sigma_from_histogram

#: A trial step below this many standard deviations asks its pass for the final sums as well: from a step s the next
#: one is ~1.5e-3 s^2 sigma here (superlinear Gauss-Newton), so after a step below 15 sigma the pass most likely ends
#: the round (:attr:`Status.STEP_TOL` or :attr:`Status.REMAINDER_TOL`); the final sums cost a fraction of a pass when
#: they are not used, a separate final pass a whole one (figures: docs/calibration.md).
FINAL_STEP_SIGMAS = 15.0
#: The contraction (ratio of a step to the step before it, both undamped, on the same data and scale) must be below
#: this for the remainder test to end a round: a ratio near 1 is not a converging sequence.
CONTRACTION_MAX = 0.5
#: A step below this many standard deviations that does not lower the cost ends the round as converged (the cost
#: then moves by less than the attitudes' own convergence changes it: ~1e-4 sigma^2 per frame), rather than being
#: retried at growing damping.
SMALL_STEP_SIGMAS = 0.01
#: Relative rounding of a pass's cost (a sum of ~10^4..10^7 terms in float64): a step whose cost is higher by less
#: than this is at the minimum and is accepted (its relative decrease, below ``ftol``, then ends the round).
COST_ROUNDING = 1e-12
#: Marquardt's damping: the first value after a failed step (and of a round that starts damped), the factor it
#: grows by after each failed trial and shrinks by after each accepted step (Marquardt 1963's x10), and the value
#: below which it is dropped to 0 (plain Gauss-Newton; 1e-12 of the diagonal changes no step beyond rounding).
INITIAL_DAMPING = 1e-6
DAMPING_GROWTH = 10.0
DAMPING_FLOOR = 1e-12
#: Most solves at growing damping for one iteration: from 1e-6, eleven growths reach 1e5, where the step is a
#: scaled gradient step ~1e-5 of the undamped one; a cost that does not fall then has no descent direction left.
MAX_DAMPING_TRIALS = 12
#: Smallest positive noise scale divided by: keeps a zero robust sigma (noise-free data) from dividing by zero.
TINY = 1e-300


class Status(enum.Enum):
    """Why a round stopped; every status but :attr:`MAX_ITER` is converged."""

    STEP_TOL = "step below the tolerance"
    REMAINDER_TOL = "step times the measured contraction below the remainder tolerance"
    SMALL_STEP = "a negligible step does not lower the cost: at the minimum"
    NO_DESCENT = "no damping lowers the cost: at the minimum"
    FTOL = "relative cost decrease below ftol"
    MAX_ITER = "iteration limit reached"

    @property
    def converged(self) -> bool:
        return self is not Status.MAX_ITER


@dataclass
class LMState:
    """What the rounds of one fit share: the iterations so far, the largest contraction measured between two
    undamped steps on the full data at a robust scale (None: none yet), and the accepted iterations' records."""

    iteration: int = 0
    contraction: float | None = None
    history: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class RoundSetup:
    """One round of :func:`lm_round`.

    evaluate(theta, final, gate_px): the pass at the camera ``theta`` (final sums when ``final``, the stars beyond
    ``gate_px`` listed). ``cols``, ``col_scale``: the estimated model-vector entries and their scales (the steps
    are solved in scaled units). ``step_tol``: :attr:`Status.STEP_TOL`'s tolerance [sigma]. ``damped``: start with
    :data:`INITIAL_DAMPING` (from a nominal camera the full step can leave every star off the detector).
    ``full_robust``: the full data at a robust scale: the contraction is measured and a small step asks its pass
    for the final sums (``gate_sigmas`` robust sigmas of the pass before). ``accelerate(theta, dx, cur)``: the
    undamped step with its geodesic acceleration, for steps above :data:`ACCELERATION_MIN_SIGMAS` (None: none)."""

    evaluate: Callable[[np.ndarray, bool, float], PassSums]
    cols: np.ndarray
    col_scale: np.ndarray
    step_tol: float
    remainder_tol: float
    ftol: float
    max_iter: int
    damped: bool
    full_robust: bool
    gate_sigmas: float
    accelerate: Callable[[np.ndarray, np.ndarray, PassSums], np.ndarray] | None = None
    progress: Callable[[dict], None] | None = None


@dataclass
class RoundResult:
    """Where a round stopped: the camera, the last pass and the camera it was made at (``theta`` less the last,
    unevaluated step after :attr:`Status.STEP_TOL` or :attr:`Status.REMAINDER_TOL`; else ``theta``)."""

    theta: np.ndarray
    last: PassSums
    theta_last: np.ndarray
    status: Status

    @property
    def converged(self) -> bool:
        return self.status.converged


@dataclass
class _Accepted:
    theta: np.ndarray
    sums: PassSums
    step_sigmas: float
    damping: float


def lm_round(setup: RoundSetup, theta: np.ndarray, cur: PassSums, state: LMState) -> RoundResult:
    """Levenberg-Marquardt iterations from the camera ``theta`` whose pass is ``cur`` until a termination test
    holds (module docstring); ``state`` counts the iterations and keeps the records across rounds."""
    damping = INITIAL_DAMPING if setup.damped else 0.0
    previous = None  # the last accepted step [sigma] when it was undamped (the contraction's denominator)
    while state.iteration < setup.max_iter:
        state.iteration += 1
        noise = max(robust_sigma_from_histogram(cur.hist), TINY)
        outcome = _iterate(setup, theta, cur, damping, noise, previous, state)
        if isinstance(outcome, RoundResult):
            return outcome
        decrease = (cur.cost - outcome.sums.cost) / max(cur.cost, TINY)
        theta, cur = outcome.theta, outcome.sums
        previous = outcome.step_sigmas if outcome.damping == 0.0 else None
        damping = outcome.damping / DAMPING_GROWTH if outcome.damping > DAMPING_FLOOR else 0.0
        _record(setup, state, cur, damping, outcome.step_sigmas)
        if decrease < setup.ftol:
            return RoundResult(theta, cur, theta, Status.FTOL)
    return RoundResult(theta, cur, theta, Status.MAX_ITER)


def _iterate(
    setup: RoundSetup,
    theta: np.ndarray,
    cur: PassSums,
    damping: float,
    noise: float,
    previous: float | None,
    state: LMState,
) -> RoundResult | _Accepted:
    """One iteration: steps at growing damping until one is accepted (step 3 of the module docstring), or the
    round's end."""
    for _trial in range(MAX_DAMPING_TRIALS):
        dx = solve_scaled(damped(cur.s, damping), cur.rhs)
        step_sigmas = float(np.sqrt(max(dx @ cur.rhs, 0.0))) / noise  # sqrt(dx^T S dx) / sigma
        if setup.accelerate is not None and damping == 0.0 and step_sigmas > ACCELERATION_MIN_SIGMAS:
            dx = setup.accelerate(theta, dx, cur)
        theta_new = theta.copy()
        theta_new[setup.cols] += dx * setup.col_scale
        if step_sigmas < setup.step_tol:
            return RoundResult(theta_new, cur, theta, Status.STEP_TOL)  # the last, tiny step applied unevaluated
        if setup.full_robust and damping == 0.0 and previous is not None:
            state.contraction = max(state.contraction or 0.0, step_sigmas / previous)
        if setup.full_robust and remainder_below(state.contraction, step_sigmas, setup.remainder_tol):
            return RoundResult(theta_new, cur, theta, Status.REMAINDER_TOL)
        final = setup.full_robust and step_sigmas < FINAL_STEP_SIGMAS
        # the gate at the robust scale of the pass at theta (that of the new pass is not known before it)
        new = setup.evaluate(theta_new, final, setup.gate_sigmas * noise if final else np.inf)
        if cost_not_higher(new.cost, cur.cost):
            return _Accepted(theta_new, new, step_sigmas, damping)
        if step_sigmas < SMALL_STEP_SIGMAS:
            return RoundResult(theta, cur, theta, Status.SMALL_STEP)
        damping = max(DAMPING_GROWTH * damping, INITIAL_DAMPING)
    return RoundResult(theta, cur, theta, Status.NO_DESCENT)


def damped(s: np.ndarray, damping: float) -> np.ndarray:
    """S with its diagonal multiplied by 1 + damping (Marquardt 1963: scale-invariant damping)."""
    out = s.copy()
    k = np.arange(s.shape[0])
    out[k, k] *= 1.0 + damping
    return out


def remainder_below(contraction: float | None, step_sigmas: float, remainder_tol: float) -> bool:
    """The remainder test: with a measured contraction below :data:`CONTRACTION_MAX`, what is left of the error
    after this step is at most step x contraction while the contraction does not grow."""
    return contraction is not None and contraction < CONTRACTION_MAX and contraction * step_sigmas < remainder_tol


def cost_not_higher(new_cost: float, cost: float) -> bool:
    """The acceptance test: a finite cost not higher than ``cost`` beyond :data:`COST_ROUNDING`."""
    return bool(np.isfinite(new_cost)) and new_cost <= cost * (1.0 + COST_ROUNDING)


def _record(setup: RoundSetup, state: LMState, cur: PassSums, damping: float, step_sigmas: float) -> None:
    """An accepted iteration's record, into the history and to the progress callback."""
    entry = {
        "iteration": state.iteration,
        "cost": cur.cost,
        "rms_px": float(np.sqrt(cur.sum_e2 / max(cur.n_obs, 1))),
        "robust_sigma_px": robust_sigma_from_histogram(cur.hist),
        "damping": damping,
        "step_sigmas": step_sigmas,
        "n_obs": cur.n_obs,
    }
    state.history.append(entry)
    if setup.progress:
        setup.progress(entry)
