"""The bundle's Levenberg-Marquardt round (hostlink.calibration.lm) on a quadratic cost it can be checked against by
hand: every termination test stops it with its own status."""

import numpy as np
import pytest

from hostlink.calibration.lm import MAX_DAMPING_TRIALS, LMState, RoundSetup, Status, lm_round
from hostlink.calibration.passes import PassSums, residual_histogram
from hostlink.calibration.robust import RAYLEIGH_MEDIAN

S = np.array([[4.0, 1.0], [1.0, 2.0]])  # the cost's curvature (the reduced normal matrix)
MINIMUM = np.array([3.0, -2.0])
#: residual lengths whose histogram gives a robust sigma of 1 (their median is the Rayleigh median)
UNIT_HIST = residual_histogram(np.full(1001, RAYLEIGH_MEDIAN))


def quadratic_pass(theta: np.ndarray, final: bool = False, gate_px: float = np.inf) -> PassSums:
    """The pass of the cost 1 + (theta - m)^T S (theta - m) / 2: S, rhs = -gradient, the cost."""
    d = theta - MINIMUM
    empty = np.zeros(0, dtype=np.int64)
    return PassSums(S, -S @ d, 1.0 + 0.5 * d @ S @ d, 0.0, 1001, 1, UNIT_HIST, empty)


def setup(evaluate=quadratic_pass, max_iter=20, **kw) -> RoundSetup:
    options = dict(step_tol=0.02, remainder_tol=5e-3, ftol=1e-12, damped=False, full_robust=False, gate_sigmas=5.0)
    options.update(kw)
    return RoundSetup(evaluate, np.array([0, 1]), np.ones(2), max_iter=max_iter, **options)


def test_a_quadratic_is_solved_in_one_step_and_the_next_one_is_below_the_tolerance():
    start = MINIMUM + np.array([1.0, 1.0])
    state = LMState()
    res = lm_round(setup(), start, quadratic_pass(start), state)
    assert res.status is Status.STEP_TOL and res.converged
    np.testing.assert_allclose(res.theta, MINIMUM, atol=1e-12)
    assert state.iteration == 2 and len(state.history) == 1  # one accepted step, one below the tolerance
    # the step's size in sigmas: sqrt(d^T S d) over the noise, 1 to the histogram's bin width (0.25 %)
    d = np.array([1.0, 1.0])
    assert state.history[0]["step_sigmas"] == pytest.approx(np.sqrt(d @ S @ d), rel=3e-3)


def test_the_iteration_limit_is_not_converged():
    start = MINIMUM + np.array([1.0, 1.0])
    res = lm_round(setup(max_iter=1), start, quadratic_pass(start), LMState())
    assert res.status is Status.MAX_ITER and not res.converged


def test_a_cost_that_never_falls_ends_with_no_descent_after_every_damping():
    calls = []

    def never(theta, final, gate_px):
        calls.append(theta)
        return PassSums(S, np.zeros(2), np.inf, 0.0, 1, 1, UNIT_HIST, np.zeros(0, dtype=np.int64))

    start = MINIMUM + np.array([10.0, 10.0])
    res = lm_round(setup(evaluate=never), start, quadratic_pass(start), LMState())
    assert res.status is Status.NO_DESCENT and len(calls) == MAX_DAMPING_TRIALS
    np.testing.assert_array_equal(res.theta, start)  # no step taken


def test_a_negligible_step_that_does_not_lower_the_cost_is_at_the_minimum():
    """A step of 0.008 sigma (above step_tol here, below SMALL_STEP_SIGMAS = 0.01) whose pass costs more: at the
    minimum, not retried at growing damping."""
    higher = PassSums(S, np.zeros(2), np.inf, 0.0, 1, 1, UNIT_HIST, np.zeros(0, dtype=np.int64))
    start = MINIMUM + np.array([0.004, 0.0])  # sqrt(4) x 0.004 = 0.008 sigma
    res = lm_round(setup(evaluate=lambda *a: higher, step_tol=1e-4), start, quadratic_pass(start), LMState())
    assert res.status is Status.SMALL_STEP
    np.testing.assert_array_equal(res.theta, start)


def test_a_step_that_lowers_the_cost_by_less_than_ftol_ends_the_round():
    start = MINIMUM + np.array([1e-7, 0.0])
    res = lm_round(setup(step_tol=0.0), start, quadratic_pass(start), LMState())
    assert res.status is Status.FTOL and res.converged


def test_a_contracting_sequence_ends_on_the_remainder_test():
    """Steps that go 70 % of the way (a model whose step is short), so each is 0.3 of the one before: once the
    contraction is measured, a step of s leaves at most 0.3 s, and when that is below remainder_tol the round ends,
    the step applied (ftol and step_tol off, so only that test can end it)."""

    def most_of_the_way(theta, final=False, gate_px=np.inf):
        p = quadratic_pass(theta)
        return PassSums(S, 0.7 * p.rhs, p.cost, 0.0, 1001, 1, UNIT_HIST, np.zeros(0, dtype=np.int64))

    start = MINIMUM + np.array([1.0, 0.0])
    state = LMState()
    options = setup(evaluate=most_of_the_way, full_robust=True, step_tol=0.0, ftol=-np.inf)
    res = lm_round(options, start, most_of_the_way(start), state)
    assert res.status is Status.REMAINDER_TOL
    assert state.contraction == pytest.approx(0.3)
    last_step = np.sqrt(max((res.theta - res.theta_last) @ S @ (res.theta - res.theta_last), 0.0))
    assert 0.3 * last_step < 5e-3 * 1.003  # the remainder test's bound (noise 1 to the histogram's bin width)
