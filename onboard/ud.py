"""U-D factorised covariance for the onboard estimator (docs/architecture.md: onboard, bounded work, no allocation).

The covariance of a K-state filter is held as P = U diag(d) U^T with U unit upper triangular (Bierman 1977,
"Factorization Methods for Discrete Sequential Estimation", ch. V; Thornton and Bierman 1980). The plain update
P - P h h^T P / s loses positive definiteness in float32 once P spans many decades; the U-D form keeps d > 0 by
construction and doubles the effective precision of P.

Every routine works in place on caller-owned arrays and in their dtype (float32 on the sensor, float64 on the host):
- :func:`bierman_update`: one scalar measurement y = h xi + v, var(v) = 1 (the caller whitens), O(K^2).
  Bierman's column recursion (alpha_j = alpha_{j-1} + f_j v_j, d_j' = d_j alpha_{j-1} / alpha_j,
  U_j' = U_j + lambda_j b_{j-1}, b_j = b_{j-1} + v_j U_j) is written with cumulative sums over columns, which
  perform the same additions in the same order as the loop, so the arithmetic is Bierman's. Every sum is in the
  order of :mod:`onboard.linalg32` (the reference model's float32 order, which a port reproduces bit for bit).
- :func:`agee_turner_update`: P + c a a^T for c >= 0 (process noise), O(K^2) (Agee and Turner 1972).
- :func:`ud_covariance`: back to a full matrix (reporting only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class BiermanWork:
    """Scratch buffers for :func:`bierman_update` (allocated once at start-up, size K)."""

    f: np.ndarray
    v: np.ndarray
    alpha: np.ndarray
    alpha_prev: np.ndarray
    cols: np.ndarray  # (K, K)


def bierman_work(n_states: int, dtype: np.dtype) -> BiermanWork:
    k = int(n_states)
    return BiermanWork(
        f=np.zeros(k, dtype),
        v=np.zeros(k, dtype),
        alpha=np.zeros(k, dtype),
        alpha_prev=np.ones(k, dtype),
        cols=np.zeros((k, k), dtype),
    )


def bierman_update(u: np.ndarray, d: np.ndarray, xi: np.ndarray, h: np.ndarray, y: float, w: BiermanWork) -> tuple:
    """Bierman's scalar measurement update, in place on (u, d, xi), for y = h . x + noise with unit variance.

    Returns ``(innovation, innovation_variance)`` = (y - h . xi, h P h + 1) as evaluated before the update
    (Bierman 1977 eq. V.3.x, the "U-D measurement update" algorithm). Work: about 6 K^2 flops.
    """
    f, v, alpha, ap, cols = w.f, w.v, w.alpha, w.alpha_prev, w.cols
    np.multiply(h, xi, out=v)  # v is scratch until v = D f below
    np.add.accumulate(v, out=v)
    innovation = (y - v[-1:]).reshape(())  # h . xi in index order (onboard.linalg32.dot)
    np.multiply(h[:, None], u, out=cols)
    np.add.accumulate(cols, axis=0, out=cols)
    f[:] = cols[-1]  # f = U^T h, each f_j summed over i in order (onboard.linalg32.vecmat)
    np.multiply(d, f, out=v)  # v = D f
    np.multiply(f, v, out=alpha)
    np.add.accumulate(alpha, out=alpha)
    alpha += 1  # alpha_j = 1 + sum_{k<=j} f_k v_k  (R = 1 after whitening)
    ap[1:] = alpha[:-1]  # alpha_{j-1}; ap[0] = 1 is set once by bierman_work
    s = alpha[-1]
    # d_j' = d_j alpha_{j-1} / alpha_j
    d *= ap
    d /= alpha
    # b_j = sum_{k<=j} v_k U_k (old columns); U_j' = U_j + lambda_j b_{j-1}, lambda_j = -f_j / alpha_{j-1}
    np.multiply(u, v, out=cols)
    np.add.accumulate(cols, axis=1, out=cols)
    xi += cols[:, -1] * (innovation / s)  # gain = b_K / alpha_K
    f /= ap  # f now holds -lambda
    cols[:, :-1] *= f[1:]
    u[:, 1:] -= cols[:, :-1]
    return innovation, s


def agee_turner_update(u: np.ndarray, d: np.ndarray, a: np.ndarray, c: float) -> None:
    """In place: U D U^T <- U D U^T + c a a^T with c >= 0 (Agee-Turner rank-one update). ``a`` is overwritten.

    Works backwards over the columns j: d_j' = d_j + c a_j^2, U_j' = (d_j U_j + c a_j a) / d_j' (rows above j),
    a <- a - a_j U_j, c <- c d_j / d_j'. Columns after the last nonzero a_j are untouched, so a random walk on the
    first state (the focal length) costs one addition.
    """
    nz = np.flatnonzero(a)
    if nz.size == 0 or c <= 0:
        return
    for j in range(int(nz[-1]), -1, -1):
        aj = a[j]
        if aj == 0:
            continue
        dj = d[j]
        dj_new = dj + c * aj * aj
        col = u[:j, j]
        tmp = a[:j] - aj * col
        col *= dj / dj_new
        col += (c * aj / dj_new) * a[:j]
        a[:j] = tmp
        c = c * dj / dj_new
        d[j] = dj_new


def ud_covariance(u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """P = U diag(d) U^T."""
    return (u * d) @ u.T
