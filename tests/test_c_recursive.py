"""The C recursive estimator (onboard/c/recursive.c, its fixed-point front end and prior.c) against the Python
sensor (onboard.recursive, onboard.fixedpoint.update, onboard.prior) over whole simulated sessions.

* Integer path: the fixed-point front end bit-exact on every linearisation of a replayed session (the camera's
  conversion, every Q30 unit vector and Q61 residual), given the Python state's linearisation point. The session is
  HOSTLINK_C_REPLAY_FRAMES frames long (default 500; the acceptance of issue 27 runs it at 10^4 on demand).
* float32 path: per update, the C and the Python update from the same saved state differ by less than the bound
  :func:`update_bound` (its reason in its docstring); the saved-state bytes round-trip exactly.
* After a session the C estimate is within 0.01 of its 1-sigma of the Python sensor's (issue 27's acceptance)."""

from __future__ import annotations

import ctypes
import math
import os
import shutil

import numpy as np
import pytest
from test_replay_cli import NOMINAL

from hostlink.portkit import estimator_c
from hostlink.portkit.estimator_c import CEstimator, FixedCamera, ptr, ref
from hostlink.portkit.vectors import gamma
from hostlink.sky.references import session_references
from hostlink.sky.simulate import seed004_config, simulate
from onboard import firmware, fixedpoint, prior, recursive
from onboard.params import ESTIMATE_NAMES, params_from_dict

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")

#: Frames of the bit-exact replay (HOSTLINK_C_REPLAY_FRAMES=10000 for the acceptance run).
REPLAY_FRAMES = int(os.environ.get("HOSTLINK_C_REPLAY_FRAMES", "500"))
#: Frames of the per-update comparison (HOSTLINK_C_UPDATE_FRAMES=10000 on demand).
UPDATE_FRAMES = int(os.environ.get("HOSTLINK_C_UPDATE_FRAMES", "300"))


@pytest.fixture(scope="module")
def nominal():
    return params_from_dict(NOMINAL)


def _frames(n_frames: int, seed: int):
    session = simulate(seed004_config(n_frames, seed=seed)).session
    refs = session_references(session)
    for rows in session.frame_slices():
        yield session.x_px[rows], session.y_px[rows], refs.r[rows], refs.usable[rows]


def update_bound(n_pairs: int, kappa_r: float, corr: np.ndarray, step_sigma: np.ndarray) -> np.ndarray:
    """Largest |x_C - x_Python| of one update, per state, in units of the posterior 1-sigma.

    Both are float32 evaluations of the same operations in different orders (numpy's BLAS and LAPACK against the
    C's plain loops; neither contracts to FMA): each is within gamma_n of exact on the data it acts on, with
    n = P + 3K + 6 (a whitening row is a P-term substitution, a Bierman update 3K + 6 dependent operations,
    hostlink/portkit/vectors.py). The whitening by the Cholesky factor L of the pair covariance R amplifies relative
    errors by kappa(L) = sqrt(kappa(R)); the least-squares solution amplifies them along the posterior's
    ill-determined combinations by sqrt(kappa(C)), C its correlation matrix (f with k1 k2 k3, the principal point with
    decentering and prism). A relative error e of the P whitened rows moves the solution by at most e (sqrt(P) +
    |step| / sigma) sigma (P unit-variance residuals; the step's own relative error). Factor 2: two evaluations."""
    eps = gamma(n_pairs + 3 * 10 + 6) * math.sqrt(kappa_r) * math.sqrt(np.linalg.cond(corr))
    return 2 * eps * (math.sqrt(max(n_pairs, 1)) + step_sigma)


def _x(state) -> np.ndarray:
    return state.x_hi.astype(np.float64) + state.x_lo.astype(np.float64)


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_c_update_is_within_the_float32_bound_of_python_at_every_frame(nominal, precision, monkeypatch):
    config = recursive.RecursiveConfig()
    c = CEstimator(nominal, ESTIMATE_NAMES, config)
    state = recursive.create(nominal, ESTIMATE_NAMES, config, np.float32)
    conds: list[float] = []
    linearise = recursive._linearise

    def spy(*args, **kwargs):
        lin = linearise(*args, **kwargs)
        conds.append(float(np.linalg.cond(lin.r.astype(np.float64))))
        return lin

    monkeypatch.setattr(recursive, "_linearise", spy)
    worst_x = worst_sigma = 0.0
    n_frames = differing = 0
    for frame in _frames(UPDATE_FRAMES, seed=3):
        blob = recursive.save_state(state)
        state = recursive.restore_state(blob, nominal, config)
        c.restore_state(blob)
        assert c.save_state() == blob  # the saved-state layout: exact both ways
        before = _x(state)
        conds.clear()
        res_py = firmware.estimator_update(state, *frame, precision)
        res_c = c.update(*frame, precision=precision)
        after_c = c.to_python()
        p_py = recursive.ud_covariance(state.u.astype(np.float64), state.d.astype(np.float64))
        p_c = recursive.ud_covariance(after_c.u.astype(np.float64), after_c.d.astype(np.float64))
        sd = np.sqrt(np.diag(p_py))
        n_frames += 1
        if (res_py.iterations, res_py.skipped, res_py.rejected_stars) != (
            res_c.iterations,
            res_c.skipped,
            res_c.rejected_stars,
        ):
            # a stopping decision taken at its threshold the other way: the two stopping points of one converging
            # iteration differ by at most the step that stopped one of them, <= iteration_tol (state units)
            differing += 1
            assert np.max(np.abs(_x(after_c) - _x(state))) <= config.iteration_tol
            continue
        assert res_c.n_pairs == res_py.n_pairs and res_c.n_used == res_py.n_used
        if res_py.skipped:
            assert np.array_equal(after_c.u, state.u) and np.array_equal(after_c.d, state.d)
            continue
        bound = update_bound(res_py.n_pairs, max(conds), p_py / np.outer(sd, sd), np.abs(_x(state) - before) / sd)
        worst_x = max(worst_x, float(np.max(np.abs(_x(after_c) - _x(state)) / sd / bound)))
        sigma_bound = update_bound(res_py.n_pairs, max(conds), p_py / np.outer(sd, sd), np.zeros(sd.size))
        worst_sigma = max(worst_sigma, float(np.max(np.abs(np.sqrt(np.diag(p_c)) / sd - 1) / sigma_bound)))
    print(f"{precision}: worst {worst_x:.3g} (state), {worst_sigma:.3g} (sigma) of the bound; {differing} decisions")
    assert worst_x <= 1.0 and worst_sigma <= 1.0, (worst_x, worst_sigma)
    assert differing <= n_frames // 100  # threshold decisions: rare (measured 1 of 300 in float32, 0 in fixed)


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_c_estimate_after_a_session_is_within_a_hundredth_of_sigma_of_python(nominal, precision):
    config = recursive.RecursiveConfig()
    c = CEstimator(nominal, ESTIMATE_NAMES, config)
    state = recursive.create(nominal, ESTIMATE_NAMES, config, np.float32)
    for frame in _frames(1000, seed=3):
        firmware.estimator_update(state, *frame, precision)
        c.update(*frame, precision=precision)
    sd = np.sqrt(np.diag(recursive.covariance(state)))
    diff = (c.state_vector() - recursive.state_vector(state))[state.idx] / sd
    assert np.max(np.abs(diff)) < 0.01, diff  # issue 27's acceptance (measured 0.0077 float32, 0.0003 fixed)
    sigma_py = np.array([recursive.sigma(state)[n] for n in ESTIMATE_NAMES])
    assert np.max(np.abs(c.sigma() / sigma_py - 1)) < 0.01  # the reported sigma too (measured 1e-4)
    assert c.to_python().updates == state.updates


def test_c_fixed_point_front_end_is_bit_exact_over_a_replayed_session(nominal, monkeypatch):
    """Every linearisation of the Python fixed-point sensor over the session, redone by the C front end from the
    same float32 linearisation point and the same integers: equal to the bit."""
    lib = estimator_c.load()
    calls: list[tuple] = []
    residuals = fixedpoint.FixedFrame.residuals

    def spy(self, theta, rows, pi, pj):
        e, theta_q = residuals(self, theta, rows, pi, pj)
        cam = fixedpoint.fixed_camera(theta, self.image_size_px)
        b = fixedpoint.pixels_to_unit_q30(self.x_steps[rows], self.y_steps[rows], cam)
        e_q61 = fixedpoint.difference_residuals_q61(b, self.r_q30[rows], pi, pj)
        calls.append((np.array(theta), self.x_steps[rows], self.y_steps[rows], self.r_q30[rows], pi, pj, b, e_q61, e))
        return e, theta_q

    monkeypatch.setattr(fixedpoint.FixedFrame, "residuals", spy)
    state = recursive.create(nominal, ESTIMATE_NAMES, recursive.RecursiveConfig(), np.float32)
    w, h = nominal.image_size_px
    n_vectors = n_residuals = 0
    for frame in _frames(REPLAY_FRAMES, seed=11):
        calls.clear()
        firmware.estimator_update(state, *frame, "fixed")
        for theta, xq, yq, rq, pi, pj, b, e_q61, e in calls:
            cam = FixedCamera()
            assert lib.fixedpoint_camera(ptr(np.ascontiguousarray(theta, np.float32)), w, h, ref(cam)) == 0
            b_c = np.zeros((xq.size, 3), np.int64)
            for k in range(xq.size):
                assert lib.fixedpoint_pixels_to_unit_q30(int(xq[k]), int(yq[k]), ref(cam), ptr(b_c[k])) == 0
            assert np.array_equal(b_c, b)
            rq = np.ascontiguousarray(rq, np.int64)
            pi32, pj32 = np.ascontiguousarray(pi, np.int32), np.ascontiguousarray(pj, np.int32)
            e_c = np.zeros(pi.size, np.int64)
            lib.fixedpoint_difference_residuals_q61(ptr(b_c), ptr(rq), ptr(pi32), ptr(pj32), pi.size, ptr(e_c))
            assert np.array_equal(e_c, e_q61)
            e_f = np.zeros(pi.size, np.float32)
            lib.fixedpoint_residuals_to_float(ptr(e_c), pi.size, ptr(e_f))
            assert np.array_equal(e_f, e)  # the filter's float32 residuals: the same rounding int64 -> float32
            n_vectors += xq.size
            n_residuals += pi.size
    assert n_vectors > 10 * REPLAY_FRAMES and n_residuals > 20 * REPLAY_FRAMES


def test_c_prior_config_and_cost_match_python(nominal):
    lib = estimator_c.load()
    config = recursive.RecursiveConfig()
    cam = estimator_c.c_camera(nominal)
    for sigma in (
        None,
        np.array([0.05, 2.0, 2.0, 1e-10, 1e-15, np.nan, 0, 0, 0, 0]),
        np.array([0.05, 2.0, 2.0, 1e-10, 1e-15, 1e-20, 1e-7, 1e-7, 1e-7, 1e-7]),
    ):
        for names in (ESTIMATE_NAMES, ("f", "x0", "y0")):
            want = prior.prior_config(config, nominal, sigma, names)
            got = estimator_c.Config()
            s = None if sigma is None else np.ascontiguousarray(sigma, np.float64)
            cfg = estimator_c.c_config(config)
            lib.prior_config(
                ref(cfg), ref(cam), None if s is None else ptr(s), estimator_c.estimated_mask(names), ref(got)
            )
            expect = estimator_c.c_config(want)
            assert _configs_equal(got, expect), (sigma, names)
    cfg = estimator_c.c_config(config)
    for n in (0, 2, 3, 10, 32, 50):
        for k in (1, 3, 10):
            assert lib.recursive_update_cost_flops(n, k, ref(cfg)) == recursive.update_cost_flops(n, k, config)


def _configs_equal(a: estimator_c.Config, b: estimator_c.Config) -> bool:
    for name, _ in a._fields_:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, ctypes.Array):
            x, y = list(x), list(y)
            if name == "prior_sigma" and not a.has_prior_sigma:
                continue
        if x != y:
            return False
    return True


def test_c_prior_refuses_the_sigmas_python_refuses():
    from onboard.params import ParameterError

    lib = estimator_c.load()
    rng = np.random.default_rng(12)
    pool = np.array([np.nan, 0.0, 1e-9, 0.5, 3.0, -0.1, -np.inf, np.inf, 1e30])
    for _ in range(300):
        sigma = np.ascontiguousarray(rng.choice(pool, 10), dtype=np.float64)
        try:
            prior.validate_sigma(sigma)
            want = -1
        except ParameterError as exc:
            want = prior.SIGMA_FILE_FIELDS.index(exc.field)
        assert lib.prior_validate_sigma(ptr(sigma)) == want
        mask = sum(1 << k for k, ok in enumerate(prior.refined_mask(sigma)) if ok)
        assert lib.prior_refined_mask(ptr(sigma)) == mask
