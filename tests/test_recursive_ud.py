"""U-D factorisation (onboard/ud.py): Bierman's update equals the textbook Kalman update, Agee-Turner equals the
rank-one sum, and float32 U-D keeps a positive definite covariance equal to float64's through a long ill-conditioned
run whose weak directions the plain float32 covariance update cannot hold."""

import numpy as np
import pytest

from onboard.ud import agee_turner_update, bierman_update, bierman_work, ud_covariance


def ud_factor(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """P = U diag(d) U^T for a symmetric positive definite P (the test's start states; the estimator builds its
    U-D factors from a diagonal prior and never factors a full matrix)."""
    p = np.array(p, copy=True)
    k = p.shape[0]
    u = np.eye(k, dtype=p.dtype)
    d = np.zeros(k, dtype=p.dtype)
    for j in range(k - 1, -1, -1):
        d[j] = p[j, j]
        u[:j, j] = p[:j, j] / d[j]
        p[:j, :j] -= d[j] * np.outer(u[:j, j], u[:j, j])
    return u, d


def _random_spd(rng, k, decades):
    q, _ = np.linalg.qr(rng.normal(size=(k, k)))
    return (q * np.logspace(0, -decades, k)) @ q.T


def test_bierman_update_equals_kalman_covariance_update_in_float64():
    rng = np.random.default_rng(1)
    p = _random_spd(rng, 10, 6)
    u, d = ud_factor(p)
    x = rng.normal(size=10)
    h = rng.normal(size=10)
    y = 0.7
    s_ref = h @ p @ h + 1.0
    gain = p @ h / s_ref
    p_ref = p - np.outer(gain, gain) * s_ref
    x_ref = x + gain * (y - h @ x)
    innov, s = bierman_update(u, d, x, h, y, bierman_work(10, np.float64))
    # float64 with a condition number of 1e6: agreement to 1e-9 relative is many digits of margin
    assert abs(s - s_ref) < 1e-12 * s_ref
    assert np.allclose(ud_covariance(u, d), p_ref, rtol=1e-9, atol=1e-9 * np.abs(p).max())
    assert np.allclose(x, x_ref, rtol=1e-12, atol=1e-12)
    assert np.all(np.tril(u, -1) == 0) and np.all(np.diag(u) == 1)


def test_agee_turner_adds_a_rank_one_term():
    rng = np.random.default_rng(2)
    p = _random_spd(rng, 6, 4)
    u, d = ud_factor(p)
    a = rng.normal(size=6)
    agee_turner_update(u, d, a.copy(), 0.3)
    assert np.allclose(ud_covariance(u, d), p + 0.3 * np.outer(a, a), rtol=1e-12, atol=1e-14)


def _long_ill_conditioned_run(seed: int):
    """4000 unit-noise scalar measurements on 6 states whose information spans 1e0..1e10 along directions that mix
    the states (as focal length, radial terms and principal point do after many frames): the float64 covariance and
    the float32 U-D factors after the run."""
    rng = np.random.default_rng(seed)
    k = 6
    q, _ = np.linalg.qr(rng.normal(size=(k, k)))
    hs = rng.normal(size=(4000, k)) @ (q * np.logspace(0, 5, k)).T
    p64 = np.eye(k)
    for h in hs:
        p64 -= np.outer(p64 @ h, p64 @ h) / (h @ p64 @ h + 1)
    u = np.eye(k, dtype=np.float32)
    d = np.ones(k, np.float32)
    x = np.zeros(k, np.float32)
    w = bierman_work(k, np.float32)
    for h in hs.astype(np.float32):
        bierman_update(u, d, x, h, np.float32(0), w)
    return hs, p64, u, d


def _variance_errors(p: np.ndarray, p64: np.ndarray) -> np.ndarray:
    """Relative error of the variance of ``p`` along each eigen-direction of the float64 reference ``p64``."""
    ev, vecs = np.linalg.eigh(p64)
    return np.abs(np.einsum("ki,kl,li->i", vecs, p, vecs) / ev - 1)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_ud_float32_keeps_a_positive_definite_covariance_equal_to_float64_on_a_long_ill_conditioned_run(seed):
    _, p64, u, d = _long_ill_conditioned_run(seed)
    p_ud = ud_covariance(u.astype(np.float64), d.astype(np.float64))
    # what the U-D form guarantees by construction: d > 0 and U unit upper triangular, so P = U D U^T is symmetric
    # positive definite, whatever the rounding
    assert np.all(d > 0) and np.all(np.diag(u) == 1) and np.all(np.tril(u, -1) == 0)
    assert np.linalg.eigvalsh(p_ud).min() > 0
    # and it holds the float64 covariance along every direction, the weakest (variance 2.5e-14, 1e10 below the
    # strongest) included: 4000 updates of a few float32 roundings (6e-8) each accumulate like a random walk to a few
    # 1e-4 relative (measured 1e-4..3.7e-3 over 8 seeds); 1e-2 leaves room for other summation orders (numpy, BLAS)
    assert _variance_errors(p_ud, p64).max() < 1e-2


def test_the_plain_float32_update_loses_the_weak_directions_of_an_ill_conditioned_covariance():
    # The plain update P - P h h^T P / s in float32 rounds every element of P to ~6e-8 of its largest eigenvalue.
    # When P's condition number exceeds 1 / eps_float32 = 1.7e7 by far (here 1e10), the variance along its weakest
    # direction is below that rounding, so the plain form cannot hold it: it comes out wrong by many times its own
    # size (measured 25x..680x over 8 seeds, sign random), on any numpy, while U-D holds it (test above).
    hs, p64, _, _ = _long_ill_conditioned_run(3)
    ev = np.linalg.eigvalsh(p64)
    assert ev[-1] / ev[0] > 1e9  # the premise: far beyond float32's 1.7e7
    p32 = np.eye(6, dtype=np.float32)
    for h in hs.astype(np.float32):
        ph = p32 @ h
        p32 = p32 - np.outer(ph, ph) / (h @ ph + np.float32(1))
    assert _variance_errors(p32.astype(np.float64), p64)[0] > 1.0  # the weakest direction's variance is lost
