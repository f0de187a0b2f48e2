"""U-D factorisation (onboard/ud.py): Bierman's update equals the textbook Kalman update, Agee-Turner equals the
rank-one sum, and float32 U-D survives a long ill-conditioned run that breaks the plain covariance update."""

import numpy as np

from onboard.ud import agee_turner_update, bierman_update, bierman_work, ud_covariance, ud_factor


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


def test_ud_float32_stays_accurate_where_the_plain_update_loses_positive_definiteness():
    # 4000 unit-noise scalar measurements on 6 states whose information spans 1e0..1e10 along directions that mix
    # the states (as focal length, radial terms and principal point do after many frames). The plain float32 update
    # P - P h h^T P / s ends with a negative eigenvalue (an impossible covariance, the start of divergence); the
    # float32 U-D update keeps every variance within 1e-3 relative of the float64 reference.
    rng = np.random.default_rng(3)
    k = 6
    q, _ = np.linalg.qr(rng.normal(size=(k, k)))
    hs = rng.normal(size=(4000, k)) @ (q * np.logspace(0, 5, k)).T
    p64 = np.eye(k)
    for h in hs:
        p64 -= np.outer(p64 @ h, p64 @ h) / (h @ p64 @ h + 1)
    p32 = np.eye(k, dtype=np.float32)
    for h in hs.astype(np.float32):
        ph = p32 @ h
        p32 = p32 - np.outer(ph, ph) / (h @ ph + np.float32(1))
    u = np.eye(k, dtype=np.float32)
    d = np.ones(k, np.float32)
    x = np.zeros(k, np.float32)
    w = bierman_work(k, np.float32)
    for h in hs.astype(np.float32):
        bierman_update(u, d, x, h, np.float32(0), w)
    rel_ud = np.abs(np.diag(ud_covariance(u.astype(float), d.astype(float))) / np.diag(p64) - 1)
    assert np.all(d > 0)
    assert rel_ud.max() < 1e-3  # measured 1.5e-4: a few float32 ulp per update, no growth
    assert np.linalg.eigvalsh(p32.astype(float)).min() < 0  # the plain form is no longer a covariance
