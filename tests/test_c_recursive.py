"""The C recursive estimator (onboard/c/recursive.c, its fixed-point front end and prior.c) against the Python
sensor (onboard.recursive, onboard.fixedpoint.update, onboard.prior) over whole simulated sessions.

Both evaluate the float32 filter in the order onboard.linalg32 states (every sum from its first term in index order,
every product and sum rounded on its own: numpy per ufunc call, the C with -ffp-contract=off; Cholesky and forward
substitution column by column), and the fixed-point front end in integers, so they are bit-exact:

* the whole estimator: the saved-state bytes after every frame of a replayed session, and every frame's result,
  equal in float32 and fixed, HOSTLINK_C_REPLAY_FRAMES frames long (default 500; the acceptance of issue 27 runs it
  at 10^4 on demand: ``HOSTLINK_C_REPLAY_FRAMES=10000 pytest tests/test_c_recursive.py -k bit_exact``);
* the integer front end's internals on every linearisation (Q30 unit vectors, Q61 residuals);
* a configuration that runs the rarer paths (process noise through Agee-Turner, a parameter subset, the drift
  detector switching on, the burn-in ending, a refined prior)."""

from __future__ import annotations

import ctypes
import os
import shutil
from dataclasses import replace

import numpy as np
import pytest
from test_replay_cli import NOMINAL

from hostlink.portkit import estimator_c
from hostlink.portkit.estimator_c import CEstimator, FixedCamera, ptr, ref
from hostlink.sky.references import session_references
from hostlink.sky.simulate import seed004_config, simulate
from onboard import firmware, fixedpoint, prior, recursive
from onboard.params import ESTIMATE_NAMES, params_from_dict

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) on this machine")

#: Frames of the bit-exact replays (HOSTLINK_C_REPLAY_FRAMES=10000 for the acceptance run).
REPLAY_FRAMES = int(os.environ.get("HOSTLINK_C_REPLAY_FRAMES", "500"))


@pytest.fixture(scope="module")
def nominal():
    return params_from_dict(NOMINAL)


def _frames(n_frames: int, seed: int):
    session = simulate(seed004_config(n_frames, seed=seed)).session
    refs = session_references(session)
    for rows in session.frame_slices():
        yield session.x_px[rows], session.y_px[rows], refs.r[rows], refs.usable[rows]


def _results_equal(a: recursive.FrameResult, b: recursive.FrameResult) -> bool:
    """Every field equal, the mean NIS too (NaN, on a frame without an update, equals NaN)."""
    same_nis = a.nis == b.nis or (np.isnan(a.nis) and np.isnan(b.nis))
    return same_nis and replace(a, nis=0.0) == replace(b, nis=0.0)


def _replay_both(nominal, names, config, frames, precision: str) -> tuple[int, int, CEstimator, object]:
    """Run the Python sensor and the C estimator side by side from the same start; return (frames, frames whose saved
    state or result differ, the C estimator, the Python state). Every 50th frame both restart from the Python's saved
    bytes (as after a power cycle; the bytes hold nis_sum in float32, so both restart from the same rounding), and
    the C's bytes must then be those bytes."""
    c = CEstimator(nominal, names, config)
    state = recursive.create(nominal, names, config, np.float32)
    assert c.save_state() == recursive.save_state(state)
    n_frames = differing = 0
    for frame in frames:
        res_py = firmware.estimator_update(state, *frame, precision)
        res_c = c.update(*frame, precision=precision)
        blob = recursive.save_state(state)
        same = c.save_state() == blob and _results_equal(res_c, res_py)
        differing += not same
        n_frames += 1
        if n_frames % 50 == 0:  # a power cycle of both: the saved-state layout, exact both ways
            state = recursive.restore_state(blob, nominal, config)
            c.restore_state(blob)
            assert c.save_state() == blob
    return n_frames, differing, c, state


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_c_estimator_is_bit_exact_with_python_after_every_frame(nominal, precision):
    config = recursive.RecursiveConfig()
    n_frames, differing, c, state = _replay_both(
        nominal, ESTIMATE_NAMES, config, _frames(REPLAY_FRAMES, seed=11), precision
    )
    assert n_frames == REPLAY_FRAMES and differing == 0, f"{precision}: {n_frames} frames, {differing} differing"
    assert state.updates > 0.9 * n_frames  # the session updates the filter: a comparison of something
    # the estimate after the session: the same float32 state, read in double by the same operations
    assert np.array_equal(c.state_vector(), recursive.state_vector(state))
    # the 1-sigma: the diagonal of U D U^T summed in double in two orders (C loops, numpy's matmul) from the same
    # float32 U and D; its terms are all positive, so each is within gamma_10 (1.1e-15) of exact
    sigma_py = np.array([recursive.sigma(state)[n] for n in ESTIMATE_NAMES])
    assert np.allclose(c.sigma(), sigma_py, rtol=1e-14, atol=0)


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_c_estimator_is_bit_exact_on_the_rarer_paths(nominal, precision):
    """Process noise on every estimated parameter (Agee-Turner each frame), four of the ten parameters, a short
    burn-in and a drift window with a threshold low enough that the focal-drift detector switches on, then a
    refined prior (no burn-in, prior_config)."""
    names = ("f", "x0", "y0", "k1")
    config = replace(
        recursive.RecursiveConfig(),
        process_noise=(1e-6, 1e-3, 1e-3, 1e-12, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        burn_in_frames=40,
        drift_window_frames=30,
        drift_start_frames=50,
        drift_threshold=0.5,
    )
    n_frames, differing, c, state = _replay_both(nominal, names, config, _frames(200, seed=5), precision)
    assert n_frames == 200 and differing == 0
    assert state.drift_on  # the detector's path ran (and switched on the focal random walk)
    sigma = np.array([0.05, 2.0, 2.0, 1e-10, 1e-15, 1e-20, 1e-7, 1e-7, 1e-7, 1e-7])
    refined = prior.prior_config(recursive.RecursiveConfig(), nominal, sigma, ESTIMATE_NAMES)
    n_frames, differing, _, _ = _replay_both(nominal, ESTIMATE_NAMES, refined, _frames(100, seed=6), precision)
    assert n_frames == 100 and differing == 0


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
