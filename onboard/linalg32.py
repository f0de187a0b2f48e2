"""Sums, products and factorisations in a stated operation order: the reference model's float32 order, which a port
reproduces for bit-exact results (docs/port-kit.md, section 5: "The order").

numpy's matmul, dot, einsum and linalg hand their sums to BLAS and LAPACK, and ``sum``/``mean`` sum pairwise: the
order of the additions (and whether a product is fused into an addition, FMA) then depends on the library, the
vector width and the array's alignment, and no C loop can reproduce it. Every sum here is a sequential
accumulation over the reduction index, each product and each sum rounded on its own (numpy rounds every ufunc call
to its dtype; C compiled with ``-ffp-contract=off`` does the same), written as ``np.add.accumulate`` along that index
(which is sequential by definition: each partial sum is an output) and vectorised over the other indices, so a
frame costs a few numpy calls per reduction and no Python loop over the outer index.

The order, as a C port writes it (onboard/c/ud.c, interstar.c, camera.c, recursive.c):

- a sum of products ``acc = a[0] * b[0]; for k in 1..n-1: acc = acc + a[k] * b[k]`` (:func:`dot`, :func:`matvec`,
  :func:`vecmat`, :func:`matmul`, :func:`sum_seq`): from the first term, not from zero (0 + (-0) is +0, so a
  start from zero can change the sign of a zero sum), then every other term in index order;
- the Cholesky factor ``l_jj = sqrt(a_jj - l_j0 l_j0 - l_j1 l_j1 - ...)``,
  ``l_ij = (a_ij - l_i0 l_j0 - l_i1 l_j1 - ...) / l_jj``, each subtraction in order of the column index
  (:func:`cholesky_lower`; written here right-looking, column by column, which subtracts in the same order);
- forward substitution ``x_i = (b_i - l_i0 x_0 - l_i1 x_1 - ...) / l_ii`` (:func:`forward_solve`).

dtype-generic (float32 on the sensor, float64 on the host): nothing promotes. Pure numpy, no I/O.
"""

from __future__ import annotations

import numpy as np


def sum_seq(terms: np.ndarray, axis: int = -1) -> np.ndarray:
    """Sum over ``axis`` in index order from the first term: ``(t_0 + t_1) + t_2 ...``; zeros if the axis is empty."""
    terms = np.asarray(terms)
    axis = axis % terms.ndim
    if terms.shape[axis] == 0:
        return np.zeros(terms.shape[:axis] + terms.shape[axis + 1 :], dtype=terms.dtype)
    return np.add.accumulate(terms, axis=axis)[(slice(None),) * axis + (-1,)]


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum_k a[..., k] b[..., k] in index order (broadcasting over the leading axes)."""
    return sum_seq(a * b, axis=-1)


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A x for A (M, K): each row's sum over k in index order."""
    return sum_seq(a * x[None, :], axis=1)


def vecmat(h: np.ndarray, u: np.ndarray) -> np.ndarray:
    """h^T U for U (K, M): each column's sum over k in index order."""
    return sum_seq(h[:, None] * u, axis=0)


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A B for A (M, K), B (K, N): each entry's sum over k in index order."""
    return sum_seq(a[:, :, None] * b[None, :, :], axis=1)


def cholesky_lower(a: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor L of the symmetric matrix ``a`` (m, m), L L^T = a, in the order of the module docstring
    (from ``a``'s lower triangle and diagonal, as the C reads it).

    Raises np.linalg.LinAlgError (as numpy's) when a pivot is not > 0 (not positive definite, or NaN)."""
    m = a.shape[0]
    work = np.array(a, copy=True)
    lower = np.zeros_like(work)
    for j in range(m):
        pivot = work[j, j]
        if not pivot > 0:
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        ljj = np.sqrt(pivot)
        lower[j, j] = ljj
        tail = lower[j + 1 :, j]
        np.divide(work[j + 1 :, j], ljj, out=tail)
        # the trailing block loses this column's products: entry (i, m) gets a_im - l_i0 l_m0 - ... in order
        work[j + 1 :, j + 1 :] -= np.multiply.outer(tail, tail)
    return lower


def forward_solve(lower: np.ndarray, b: np.ndarray) -> np.ndarray:
    """X = L^-1 B for L (m, m) lower triangular and B (m, c), in the order of the module docstring."""
    out = np.array(b, copy=True)  # row i is finished before row i + 1 reads it: the work array is the result
    for i in range(lower.shape[0]):
        row = out[i]
        row /= lower[i, i]
        out[i + 1 :] -= np.multiply.outer(lower[i + 1 :, i], row)
    return out
