"""onboard.linalg32: the reference model's float32 order (sequential sums from the first term, Cholesky and forward
substitution column by column) is the order it states, and its results are those of LAPACK within the textbook
backward-error bounds (Higham, "Accuracy and Stability of Numerical Algorithms", 2nd ed.: Thm 8.5 for a triangular
solve, Thm 10.3 for Cholesky)."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.portkit.vectors import gamma
from onboard import linalg32


def _scalar_sum(terms) -> np.float32:
    """The stated order written as a scalar loop: the first term, then each further one, each sum rounded."""
    acc = np.float32(terms[0])
    for t in terms[1:]:
        acc = np.float32(acc + np.float32(t))
    return acc


def _spd(rng, n: int, dtype) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return (a @ a.T + n * np.eye(n)).astype(dtype)


def test_sums_are_sequential_from_the_first_term():
    rng = np.random.default_rng(1)
    # magnitudes over 12 decades: any other order (pairwise, 8 lanes) rounds differently on many of these rows
    terms = (rng.normal(size=(200, 61)) * 10.0 ** rng.uniform(-6, 6, size=(200, 61))).astype(np.float32)
    got = linalg32.sum_seq(terms, axis=1)
    assert got.dtype == np.float32
    assert all(got[r] == _scalar_sum(terms[r]) for r in range(terms.shape[0]))
    assert np.any(got != np.sum(terms, axis=1))  # the input does tell orders apart
    a, x = terms[:, :10], terms[0, :10]
    assert np.array_equal(linalg32.matvec(a, x), [_scalar_sum(a[r] * x) for r in range(a.shape[0])])
    u = terms[:10, :7]
    assert np.array_equal(linalg32.vecmat(x, u), [_scalar_sum(x * u[:, c]) for c in range(7)])
    assert np.array_equal(
        linalg32.matmul(a[:5], u), [[_scalar_sum(a[r] * u[:, c]) for c in range(7)] for r in range(5)]
    )
    assert np.array_equal(linalg32.dot(a, a), [_scalar_sum(a[r] * a[r]) for r in range(a.shape[0])])
    # a sum of negative zeros is -0 (from the first term; a start from +0 would make it +0), the C's order too
    assert np.signbit(linalg32.sum_seq(np.array([-0.0, -0.0], np.float32)))
    assert linalg32.sum_seq(np.zeros((3, 0), np.float32)).tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("n", [1, 3, 25, 61])
def test_cholesky_is_lapacks_within_the_backward_error_bound(n):
    rng = np.random.default_rng(n)
    a64 = _spd(rng, n, np.float64)
    assert np.allclose(linalg32.cholesky_lower(a64), np.linalg.cholesky(a64), rtol=1e-12, atol=1e-12)
    a = a64.astype(np.float32)
    lower = linalg32.cholesky_lower(a)
    assert lower.dtype == np.float32 and np.array_equal(lower, np.tril(lower))
    l64 = lower.astype(np.float64)
    # |A - L L^T| <= gamma_{n+1} |L| |L^T| (Higham Thm 10.3), float32's unit roundoff
    bound = gamma(n + 1) * (np.abs(l64) @ np.abs(l64).T)
    assert np.all(np.abs(a.astype(np.float64) - l64 @ l64.T) <= bound)
    # each entry in the stated order: l_ij = (a_ij - l_i0 l_j0 - ...) / l_jj, l_jj = sqrt(a_jj - l_j0^2 - ...)
    i, j = n - 1, max(n - 2, 0)
    acc = a[i, j]
    for c in range(j):
        acc = np.float32(acc - np.float32(lower[i, c] * lower[j, c]))
    want = np.sqrt(acc) if i == j else np.float32(acc / lower[j, j])
    assert lower[i, j] == want


def test_cholesky_refuses_what_lapack_refuses():
    for a in (np.array([[1.0, 2.0], [2.0, 1.0]], np.float32), np.array([[np.nan]], np.float32)):
        with pytest.raises(np.linalg.LinAlgError):
            linalg32.cholesky_lower(a)


def test_forward_substitution_is_a_solve_within_the_backward_error_bound():
    rng = np.random.default_rng(7)
    n = 45
    lower = np.linalg.cholesky(_spd(rng, n, np.float64))
    b = rng.normal(size=(n, 11))
    assert np.allclose(linalg32.forward_solve(lower, b), np.linalg.solve(lower, b), rtol=1e-10, atol=1e-12)
    l32, b32 = lower.astype(np.float32), b.astype(np.float32)
    x = linalg32.forward_solve(l32, b32)
    assert x.dtype == np.float32
    # (L + dL) x = b with |dL| <= gamma_n |L| (Higham Thm 8.5): |b - L x| <= gamma_n |L| |x|
    l64, x64 = l32.astype(np.float64), x.astype(np.float64)
    assert np.all(np.abs(b32.astype(np.float64) - l64 @ x64) <= gamma(n) * (np.abs(l64) @ np.abs(x64)))
    row = 17  # x_i = (b_i - l_i0 x_0 - l_i1 x_1 - ...) / l_ii, in that order
    acc = b32[row, 3]
    for c in range(row):
        acc = np.float32(acc - np.float32(l32[row, c] * x[c, 3]))
    assert x[row, 3] == np.float32(acc / l32[row, row])
