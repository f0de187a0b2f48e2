"""The normal equations of the bundle adjustment: accumulation, Schur complement, solve, covariance.

    [ U    B ] [dtheta]     [g    ]
    [ B^T  A ] [dphi  ] = - [g_phi]

U, g: the camera's blocks (K x K, K); A: block diagonal, one 3 x 3 block per frame; B: K x 3 per frame. The
attitude blocks are eliminated by the Schur complement S = U - sum_f B_f A_f^-1 B_f^T, accumulated over chunks of
frames, so the memory of a pass does not grow with the number of frames and its time is linear in it (Triggs et al.,
"Bundle adjustment - a modern synthesis", 2000, sec. 6). The terms summed are :mod:`hostlink.calibration.model`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks
from hostlink.calibration.frames import inverse_3x3, per_frame_products
from hostlink.calibration.model import DEFAULT_CHUNK_OBS, observation_terms


@dataclass
class NormalBlocks:
    u: np.ndarray  # (K, K)
    g: np.ndarray  # (K,)
    a: np.ndarray  # (M, 3, 3)
    b: np.ndarray  # (M, K, 3)
    g_phi: np.ndarray  # (M, 3)
    e: np.ndarray  # (N, 2) residuals at the linearisation point


def accumulate_normals(
    data: CalibrationData,
    theta: np.ndarray,
    attitudes: np.ndarray,
    cols: np.ndarray,
    weights: np.ndarray,
    col_scale: np.ndarray,
    chunk_obs: int = DEFAULT_CHUNK_OBS,
    values: np.ndarray | None = None,
) -> NormalBlocks:
    """Weighted normal-equation blocks, one chunk of frames at a time (memory bounded by ``chunk_obs``).

    Camera columns are multiplied by ``col_scale`` (the step is solved in scaled units). ``values``: (N, 2) vectors
    whose gradient sums g = sum J_t^T W v and g_phi = sum J_phi^T W v the blocks carry instead of the residuals'
    (and ``e`` holds them)."""
    k = cols.shape[0]
    m = data.n_frames
    starts = data.frame_starts
    counts = data.counts
    blocks = NormalBlocks(
        np.zeros((k, k)),
        np.zeros(k),
        np.zeros((m, 3, 3)),
        np.zeros((m, k, 3)),
        np.zeros((m, 3)),
        np.zeros((data.n_obs, 2)),
    )
    for f0, f1 in frame_chunks(starts, chunk_obs):
        a, b = int(starts[f0]), int(starts[f1])
        att = np.repeat(attitudes[f0:f1], counts[f0:f1], axis=0)
        e, jt, jp = observation_terms(data.x_px[a:b], data.y_px[a:b], data.r[a:b], att, theta, cols)
        e = e if values is None else values[a:b]
        u, g, blocks.a[f0:f1], blocks.b[f0:f1], blocks.g_phi[f0:f1] = normal_blocks(
            e, jt, jp, weights[a:b], starts[f0 : f1 + 1] - a, col_scale
        )
        blocks.u += u
        blocks.g += g
        blocks.e[a:b] = e
    return blocks


def normal_blocks(
    e: np.ndarray,
    jt: np.ndarray,
    jp: np.ndarray,
    w: np.ndarray,
    local_starts: np.ndarray,
    col_scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The weighted normal-equation blocks of a run of whole frames from their terms (:func:`observation_terms`):
    U = sum J_t^T W J_t, g = sum J_t^T W e (K x K, K), and per frame A = sum J_phi^T W J_phi, B = sum J_t^T W J_phi,
    g_phi = sum J_phi^T W e; ``local_starts`` are the frames' first rows (one more entry: the row count). The
    Jacobians are taken entry by entry, (2, K, n) and (2, 3, n) (:func:`observation_terms` stores them so: no copy):
    U and g are two matrix products, and each frame's 3K entries of B, six of A and three of g_phi are rows of
    products summed along the frame's rows (:func:`_frame_sums`). ``col_scale``: the camera columns multiplied by
    it, applied to the sums (K x K, K and K x 3 entries per frame) rather than to the per-star Jacobian."""
    k = jt.shape[2]
    j = np.ascontiguousarray(jt.transpose(1, 2, 0))
    p = np.ascontiguousarray(jp.transpose(1, 2, 0))
    e_rows = np.ascontiguousarray(e.T)
    jw = j * w
    u = jw[0] @ j[0].T + jw[1] @ j[1].T
    g = jw[0] @ e_rows[0] + jw[1] @ e_rows[1]
    pw = p * w
    rows = np.empty((3 * k + 9, e.shape[0]))
    for c in range(3):
        block = rows[c * k : (c + 1) * k]
        np.multiply(j[0], pw[0, c], out=block)
        block += j[1] * pw[1, c]
    _attitude_rows(p, pw, e_rows, rows[3 * k :])
    sums = _frame_sums(rows, local_starts)
    b = np.ascontiguousarray(sums[: 3 * k].reshape(3, k, -1).transpose(2, 1, 0))
    a, g_phi = _attitude_blocks(sums[3 * k :])
    if col_scale is not None:
        u, g, b = u * np.outer(col_scale, col_scale), g * col_scale, b * col_scale[None, :, None]
    return u, g, a, b, g_phi


#: The entries (i, j) of a symmetric 3 x 3 matrix stored once each (the upper triangle), and where each of the nine
#: entries is found among them
_SYM_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


_SYM_INDEX = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])


def attitude_normal(
    e: np.ndarray, jp: np.ndarray, w: np.ndarray, frame_starts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, A = sum J_phi^T W J_phi (M, 3, 3) and g_phi = sum J_phi^T W e (M, 3) of the residuals ``e`` (n, 2)
    and their attitude Jacobian ``jp`` (n, 2, 3) with the weights ``w``: the blocks of :func:`normal_blocks` an
    attitude step needs, the same rows of products summed the same way (:func:`_attitude_rows`)."""
    p = np.ascontiguousarray(jp.transpose(1, 2, 0))
    rows = np.empty((9, e.shape[0]))
    _attitude_rows(p, p * w, np.ascontiguousarray(e.T), rows)
    return _attitude_blocks(_frame_sums(rows, frame_starts))


def _attitude_rows(p: np.ndarray, pw: np.ndarray, e_rows: np.ndarray, out: np.ndarray) -> None:
    """Each star's six distinct entries of J_phi^T W J_phi and three of J_phi^T W e as rows (9, n) of ``out``, from
    the attitude Jacobian entry by entry ``p`` (2, 3, n), the same weighted ``pw`` and the residuals (2, n)."""
    for n, (i, j) in enumerate(_SYM_PAIRS):
        np.multiply(pw[0, i], p[0, j], out=out[n])
        out[n] += pw[1, i] * p[1, j]
    for i in range(3):
        np.multiply(pw[0, i], e_rows[0], out=out[6 + i])
        out[6 + i] += pw[1, i] * e_rows[1]


def _attitude_blocks(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (M, 3, 3) and g_phi (M, 3) from the per-frame sums (9, M) of :func:`_attitude_rows`."""
    return sums[_SYM_INDEX].T.reshape(-1, 3, 3), np.ascontiguousarray(sums[6:].T)


def _frame_sums(rows: np.ndarray, frame_starts: np.ndarray) -> np.ndarray:
    """The sums (r, M) of rows (r, n) along each frame's stars (contiguous columns from ``frame_starts``); a frame
    without stars sums to zero (reduceat would give it a column of its own)."""
    sums = np.zeros((rows.shape[0], frame_starts.shape[0] - 1))
    filled = np.diff(frame_starts) > 0
    if np.any(filled):
        sums[:, filled] = np.add.reduceat(rows, frame_starts[:-1][filled], axis=1)
    return sums


def unit_weight_normal(
    blocks: NormalBlocks,
    s: np.ndarray,
    jt: np.ndarray,
    jp: np.ndarray,
    w: np.ndarray,
    frame_starts: np.ndarray,
    col_scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The reduced normal matrix and diag(U) with unit weights (the covariance's), from the weighted ones: the
    ``blocks`` of :func:`normal_blocks` with the weights ``w`` of the terms ``jt``, ``jp`` and their Schur complement
    ``s`` (:func:`reduced_normal`). Only the stars with w < 1 (Huber's: ~1 % at 3 sigma) and their frames F are
    summed again:

        S_1 = S_w + X - sum_(f in F) (B'_f A'_f^-1 B'_f^T - B_f A_f^-1 B_f^T)

    with X = sum_(w_k < 1) (1 - w_k) J_t,k^T J_t,k, and A'_f, B'_f the frame's blocks plus its stars' (1 - w_k)
    terms. The same matrix as :func:`reduced_normal` of :func:`normal_blocks` with unit weights, to the rounding of
    the sums. ``col_scale``: that given to :func:`normal_blocks` (``jt`` unscaled)."""
    down = np.flatnonzero(w < 1.0)
    if down.size == 0:
        return s.copy(), np.diag(blocks.u).copy()
    k = jt.shape[2]
    dw = 1.0 - w[down]
    jt_d, jp_d = jt[down], jp[down]
    if col_scale is not None:
        jt_d *= col_scale
    x = (jt_d * dw[:, None, None]).reshape(-1, k).T @ jt_d.reshape(-1, k)
    frame = np.searchsorted(frame_starts, down, side="right") - 1  # each star's frame (increasing)
    affected, first = np.unique(frame, return_index=True)
    extra = per_frame_products(np.concatenate([jt_d, jp_d], axis=2), jp_d, dw, np.append(first, down.size))
    a_w, b_w = blocks.a[affected], blocks.b[affected]
    a_1, b_1 = a_w + extra[:, k:, :], b_w + extra[:, :k, :]

    def schur_sum(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.tensordot(b @ inverse_3x3(a), b, axes=([0, 2], [0, 2]))

    u_1 = blocks.u + x
    return s + x - schur_sum(a_1, b_1) + schur_sum(a_w, b_w), np.diag(u_1).copy()


def reduced_normal(blocks: NormalBlocks, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Schur complement over the attitude blocks, with Marquardt damping (diag scaled by 1 + damping).

    Returns (S, rhs, A^-1) with S dtheta = rhs and A^-1 (M, 3, 3) the damped attitude blocks' inverses, for the
    back substitution dphi_f = -A_f^-1 (B_f^T dtheta + g_phi,f)."""
    a = blocks.a.copy()
    idx = np.arange(3)
    a[:, idx, idx] *= 1.0 + damping
    u = blocks.u.copy()
    kdx = np.arange(u.shape[0])
    u[kdx, kdx] *= 1.0 + damping
    a_inv = inverse_3x3(a)
    w = blocks.b @ a_inv
    s = u - np.tensordot(w, blocks.b, axes=([0, 2], [0, 2]))
    rhs = -blocks.g + np.einsum("mkj,mj->k", w, blocks.g_phi)
    return s, rhs, a_inv


def solve_scaled(s: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve S x = rhs after Jacobi equilibration; a (near-)singular S gets the minimum-norm solution."""
    d = np.sqrt(np.maximum(np.diag(s), 1e-300))
    ss = s / d[:, None] / d[None, :]
    try:
        x = np.linalg.solve(ss, rhs / d)
        if not np.all(np.isfinite(x)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(ss, rhs / d, rcond=1e-14)[0]
    return x / d


def covariance_from_normal(s: np.ndarray, sigma_px: float) -> np.ndarray:
    """sigma^2 S^-1 via the Jacobi-equilibrated pseudo-inverse (a null direction gets infinite variance on the
    diagonal of the parameters it involves, rather than a silent finite number)."""
    d = np.sqrt(np.maximum(np.diag(s), 1e-300))
    ss = s / d[:, None] / d[None, :]
    vals, vecs = np.linalg.eigh(ss)
    tiny = vals <= vals.max() * 1e-15
    inv_vals = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, vals))
    cov = (vecs * inv_vals) @ vecs.T
    if np.any(tiny):
        null = np.any(np.abs(vecs[:, tiny]) > 1e-3, axis=1)
        cov[null, null] = np.inf
    return sigma_px**2 * cov / d[:, None] / d[None, :]
