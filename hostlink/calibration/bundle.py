"""The default calibration: a bundle adjustment over the camera and the attitude of every frame.

Measurement model, per identified star k of frame f (docs/camera-model.md):

    q(x_k, y_k; theta) = F (C_f r_k)_xy / (C_f r_k)_z

with q the ideal offsets of the measured centroid (``onboard.camera.ideal_offset_jacobians``), F = theta[0] in
pixels and C_f the attitude (b = C r). The residual is whitened into measured pixels,

    e_k = Jc_k^-1 (q_k - p_k),     Jc = dq/d(x, y),

so that isotropic centroid noise sigma gives e_k ~ N(0, sigma^2 I) to first order, and least squares is maximum
likelihood. Unknowns: the selected camera parameters and a 3-parameter rotation increment per frame
(C <- exp(-[dphi x]) C). Levenberg-Marquardt steps solve the normal equations

    [ U    B ] [dtheta]     [g    ]
    [ B^T  A ] [dphi  ] = - [g_phi]

where A is block diagonal (one 3 x 3 block per frame). The attitude blocks are eliminated by the Schur complement
S = U - sum_f B_f A_f^-1 B_f^T, accumulated over chunks of frames, so the memory of a pass does not grow with the
number of frames and its time is linear in it (Triggs et al., "Bundle adjustment - a modern synthesis", 2000, sec. 6).

Robustness: interstar voting before the fit, Huber weights during it, gating after it (``robust``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from hostlink.calibration.data import (
    MIN_STARS_PER_FRAME,
    CalibrationData,
    frame_chunks,
    measured_directions,
    take_frames,
)
from hostlink.calibration.frames import (
    apply_attitude_increment,
    inverse_3x3,
    per_frame_products,
    triad_attitudes,
    vector_norms,
    wahba_attitudes,
)
from hostlink.calibration.robust import RAYLEIGH_MEDIAN, huber_rho, huber_weights, vote_consistent_stars
from onboard.camera import (
    distortion_partials,
    distortion_partials_applied_jacobian,
    ideal_offset_jacobians,
    ideal_offsets,
    offsets_to_unit,
)
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Most stars processed at once in a pass over the data: bounds the working arrays (~1.5 kB per star, ~8 MB per pass).
#: Small enough that each temporary (~1 MB) stays in cache and is reused by the allocator rather than mapped afresh
#: and page-faulted in: a pass at 5000 stars costs ~0.6 of one at 20 000 (measured at 10^4 frames; 4000-10 000 are
#: all within 10 % of it), large enough that numpy's per-call overhead stays small.
DEFAULT_CHUNK_OBS = 5_000


@dataclass(frozen=True)
class BundleOptions:
    estimate: tuple[str, ...] = ESTIMATE_NAMES
    max_iter: int = 100
    noise_px: float | None = None  # known centroid noise per axis; None: estimated from the residuals
    huber_k: float = 3.0  # Huber threshold in robust sigmas (efficiency ~99.5 % for Gaussian noise)
    gate: float = 5.0  # residuals beyond this many robust sigmas are dropped (2-D Gaussian: P = 3.7e-6)
    max_gate_rounds: int = 5
    screen: bool = True  # interstar voting before the fit
    chunk_obs: int = DEFAULT_CHUNK_OBS
    ftol: float = 1e-12  # stop when the relative cost decrease of an accepted step is below this, or
    # when a step moves the camera by less than this many standard deviations (the step is applied: Gauss-Newton
    # here shrinks each step ~50-fold, so <= 4e-4 sigma is left, 1.4e-4 measured at 10^4 frames;
    # tests/test_calibration_chunked.py checks 1e-3). 0.02 rather than 0.01: the first step after a few stars are
    # gated is ~0.015 sigma, and it then ends the round on the gating pass's sums, without a pass of its own
    step_tol: float = 2e-2
    #: ... or when the step times the contraction measured between this fit's steps (:data:`CONTRACTION_MAX`) is
    #: below this many standard deviations: the step is applied, and what is left of the error is at most that
    #: product while the contraction does not grow (Gauss-Newton here converges superlinearly: steps of 10.3, 0.154
    #: sigma at 10^4 frames; 41.5, 2.33, 0.007 at 10^5). 0.005 sigma raises the camera's mean square error by
    #: 2.5e-5 of its variance; it saves the pass that would only confirm a step of ~0.15 sigma
    remainder_tol: float = 5e-3
    progress: Callable[[dict], None] | None = None


@dataclass
class BundleResult:
    theta: np.ndarray  # model vector (F in px), all 10 entries
    attitudes: np.ndarray  # (M_fit, 3, 3) for the frames of ``data``
    data: CalibrationData  # the rows and frames that were fitted (inliers)
    rows_used: np.ndarray  # (N_input,) bool: input rows kept
    rows_gated: np.ndarray  # (N_input,) bool: input rows dropped by residual gating (the rest of the drops: voting,
    # or a frame left with fewer than three stars)
    n_rejected_voting: int
    n_rejected_gating: int
    n_frames_dropped: int
    sigma_px: float  # centroid noise per axis used for the covariance
    sigma_estimated_px: float  # from the final residuals
    estimate: tuple[str, ...]
    normal: np.ndarray  # (K, K) reduced normal matrix S / 1 (unit noise), model-vector units
    normal_u_diag: np.ndarray  # (K,) diagonal of U before the attitudes are eliminated
    covariance: np.ndarray  # (K, K) sigma^2 S^-1, model-vector units
    history: list[dict] = field(default_factory=list)
    converged: bool = False


def parameter_columns(estimate: tuple[str, ...]) -> np.ndarray:
    """Indices into the model vector of the estimated parameters (ESTIMATE_NAMES order)."""
    unknown = [n for n in estimate if n not in ESTIMATE_NAMES]
    if unknown:
        raise ValueError(f"unknown parameter name(s) {', '.join(unknown)} (allowed: {','.join(ESTIMATE_NAMES)})")
    return np.array([ESTIMATE_NAMES.index(n) for n in ESTIMATE_NAMES if n in estimate], dtype=np.int64)


def parameter_scales(params: CameraParams) -> np.ndarray:
    """Characteristic size of a unit change of each model-vector entry: 1 px for F, x0, y0 and 1 px of distortion
    at the detector half-diagonal R for the rest (k1 ~ R^-3, k2 ~ R^-5, k3 ~ R^-7, p and s ~ R^-2). Steps are
    solved in these units so the normal matrix is well scaled."""
    half_diag = 0.5 * float(np.hypot(*params.image_size_px))
    return np.array([1.0, 1.0, 1.0, half_diag**-3, half_diag**-5, half_diag**-7] + [half_diag**-2] * 4)


def _projection(
    r: np.ndarray, attitude_obs: np.ndarray, focal_px: float, s: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s = C r per star, its ideal-plane projection p = F s_xy / s_z [px], and 1 / s_z. ``s``: C r when already
    computed."""
    s = rotate(attitude_obs, r) if s is None else s
    inv_z = 1.0 / s[:, 2]
    p = np.empty((s.shape[0], 2))
    for i in range(2):  # column by column: (F s_i) / s_z with the products of F s[:, :2] / s_z, at a fifth of the cost
        np.multiply(s[:, i], focal_px, out=p[:, i])
        p[:, i] *= inv_z
    return s, p, inv_z


def rotate(attitude_obs: np.ndarray, r: np.ndarray) -> np.ndarray:
    """C r for each star's (n, 3, 3) attitude and (n, 3) vector, the products written out (einsum's numbers to
    rounding, at half its cost for a few thousand stars)."""
    s = np.empty(r.shape)
    r0, r1, r2 = r[:, 0], r[:, 1], r[:, 2]
    for i in range(3):
        np.multiply(attitude_obs[:, i, 0], r0, out=s[:, i])
        s[:, i] += attitude_obs[:, i, 1] * r1
        s[:, i] += attitude_obs[:, i, 2] * r2
    return s


def _inverse_2x2(jc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Entries (i00, i01, i10, i11) of Jc^-1 for a stack of 2 x 2 matrices, written out (numpy's batched
    small-matrix routines cost more in call overhead than the arithmetic)."""
    det = jc[:, 0, 0] * jc[:, 1, 1] - jc[:, 0, 1] * jc[:, 1, 0]
    return jc[:, 1, 1] / det, -jc[:, 0, 1] / det, -jc[:, 1, 0] / det, jc[:, 0, 0] / det


def _whiten(jc_inv: tuple, j: np.ndarray) -> np.ndarray:
    """Jc^-1 J for each star: the whitening (entries (i00, i01, i10, i11), each (n,)) applied to the Jacobian rows
    ``j`` (2, K, n) stored entry by entry, as rows of K x n products (each entry's two products and one sum); a new
    (2, K, n) array."""
    i00, i01, i10, i11 = jc_inv
    out = np.empty(j.shape)
    np.multiply(j[0], i00, out=out[0])
    out[0] += j[1] * i01
    np.multiply(j[0], i10, out=out[1])
    out[1] += j[1] * i11
    return out


@dataclass(frozen=True)
class CameraTerms:
    """What the camera ``theta`` gives every star of a block, whatever its frame's attitude: the ideal offsets q
    (n, 2) [px], their Jacobian dq/dtheta (n, 2, 10), the entries (i00, i01, i10, i11) of the whitening Jc^-1 and
    the measured offsets (u, v) from the principal point [px]. Computed once per block and camera
    (:func:`camera_terms`), shared by the attitude steps and the camera's normal equations of a pass."""

    q: np.ndarray
    jq_theta: np.ndarray
    jc_inv: tuple
    u: np.ndarray
    v: np.ndarray


def camera_terms(x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray) -> CameraTerms:
    """:class:`CameraTerms` of the centroids (x, y) [px] at the camera ``theta`` (``onboard.camera``)."""
    q, jq_theta, jc = ideal_offset_jacobians(x_px, y_px, theta)
    jc_inv = _inverse_2x2(jc)
    return CameraTerms(q, jq_theta, jc_inv, x_px - theta[1], y_px - theta[2])


def observation_terms(
    x_px: np.ndarray,
    y_px: np.ndarray,
    r: np.ndarray,
    attitude_obs: np.ndarray,
    theta: np.ndarray,
    cols: np.ndarray,
    cam: CameraTerms | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals and their Jacobians for a block of stars.

    attitude_obs: (n, 3, 3) attitude of each star's frame. Returns e (n, 2) [measured px], J_theta (n, 2, K)
    with respect to the model-vector entries ``cols``, J_phi (n, 2, 3) with respect to the frame's rotation
    increment; both stored entry by entry (views of (2, K, n) and (2, 3, n) arrays: every entry's n values
    contiguous, the rows :func:`normal_blocks` multiplies and sums). J_theta is the exact derivative of e,
    including that of the whitening Jc^-1 (which depends on the principal point and the distortion): with the
    whitening held fixed, the Gauss-Newton fixed point is not the minimum of sum |e|^2 and, along the weak
    principal-point/decentering/attitude direction, lies many standard deviations from it
    (:func:`whitening_jacobian`). ``cam``: the block's :func:`camera_terms` at ``theta`` when already computed.
    """
    cam = cam if cam is not None else camera_terms(x_px, y_px, theta)
    q, jq_theta = cam.q, cam.jq_theta
    focal_px = theta[0]
    s, p, inv_z = _projection(r, attitude_obs, focal_px)
    i00, i01, i10, i11 = cam.jc_inv
    d = q - p
    e = np.stack([i00 * d[:, 0] + i01 * d[:, 1], i10 * d[:, 0] + i11 * d[:, 1]], axis=1)
    # dq/dtheta plus the whitening's part (a new array: the camera terms are shared), less dp/dF = p / F in the F
    # column (q does not depend on F, nor does the whitening: both are zero there); entry by entry, (2, K, n)
    j = whitening_jacobian(cam.u, cam.v, theta, cols, e, (i00, i01, i10, i11), whitened=False).transpose(1, 2, 0)
    jq = jq_theta.transpose(1, 2, 0)
    j += jq if _all_columns(cols, jq_theta.shape[2]) else jq[:, cols, :]
    f_col = np.flatnonzero(cols == 0)
    if f_col.size:
        j[:, f_col[0], :] -= p.T / focal_px
    return e, _whiten(cam.jc_inv, j).transpose(2, 0, 1), _attitude_jacobian(s, p, inv_z, focal_px, cam.jc_inv)


def _attitude_jacobian(s: np.ndarray, p: np.ndarray, inv_z: np.ndarray, focal_px: float, jc_inv: tuple) -> np.ndarray:
    """de/dphi (n, 2, 3) for the rotation increment of the star's frame, from s = C r, its projection p, 1 / s_z
    and the whitening Jc^-1 (entries)."""
    i00, i01, i10, i11 = jc_inv
    # dp/dphi for s -> s + phi x s: row k of dp/ds times [s]x, i.e. (dp_k/ds) x s, with
    # dp_0/ds = (F/z, 0, -p_0/z) and dp_1/ds = (0, F/z, -p_1/z)
    fz = focal_px * inv_z
    a0z, a1z = -p[:, 0] * inv_z, -p[:, 1] * inv_z
    sx, sy, sz = s[:, 0], s[:, 1], s[:, 2]
    out = np.empty((2, 3, s.shape[0]))  # entry by entry: returned as its (n, 2, 3) view
    # column by column (no stacked temporaries): c0 = (dp_0/ds) x s, c1 = (dp_1/ds) x s, then -Jc^-1 (c0, c1)
    for j, (c0, c1) in enumerate(
        ((-a0z * sy, fz * sz - a1z * sy), (a0z * sx - fz * sz, a1z * sx), (fz * sy, -fz * sx))
    ):
        out[0, j] = -(i00 * c0 + i01 * c1)
        out[1, j] = -(i10 * c0 + i11 * c1)
    return out.transpose(2, 0, 1)


def attitude_terms(
    x_px: np.ndarray,
    y_px: np.ndarray,
    r: np.ndarray,
    attitude_obs: np.ndarray,
    theta: np.ndarray,
    cam: CameraTerms | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals e (n, 2) and their attitude Jacobian J_phi (n, 2, 3) alone (the camera held): the
    per-frame attitude steps of :func:`frame_attitudes`. Same e and J_phi as :func:`observation_terms`; ``cam``:
    the block's :func:`camera_terms` when already computed (else only what e needs is)."""
    if cam is None:
        q_u, q_v = ideal_offsets(x_px, y_px, theta)
        dx_u, dx_v, dy_u, dy_v = distortion_partials(x_px - theta[1], y_px - theta[2], theta)
        jc = np.stack([np.stack([1 - dx_u, -dx_v], axis=-1), np.stack([-dy_u, 1 - dy_v], axis=-1)], axis=-2)
        jc_inv = _inverse_2x2(jc)
    else:
        q_u, q_v, jc_inv = cam.q[:, 0], cam.q[:, 1], cam.jc_inv
    s, p, inv_z = _projection(r, attitude_obs, theta[0])
    i00, i01, i10, i11 = jc_inv
    d0, d1 = q_u - p[:, 0], q_v - p[:, 1]
    e = np.stack([i00 * d0 + i01 * d1, i10 * d0 + i11 * d1], axis=1)
    return e, _attitude_jacobian(s, p, inv_z, theta[0], jc_inv)


def whitening_jacobian(
    u: np.ndarray,
    v: np.ndarray,
    theta: np.ndarray,
    cols: np.ndarray,
    e: np.ndarray,
    jc_inv: tuple,
    whitened: bool = True,
) -> np.ndarray:
    """d(Jc^-1) / d theta applied to d = Jc e: the part of de/dtheta that comes from the whitening (n, 2, K).

    Jc = I - P with P the distortion partials (``onboard.camera.distortion_partials``), so
    d(Jc^-1)/dtheta_k d = Jc^-1 (dP/dtheta_k) e, with (dP/dtheta_k) e in closed form
    (``onboard.camera.distortion_partials_applied_jacobian``: P at the unit coefficient for k1..s2, minus its
    derivative in u or v for the principal point, zero for F). ``whitened=False``: (dP/dtheta_k) e alone, before
    the product with Jc^-1 (the caller applies Jc^-1 once to the sum with dq/dtheta)."""
    pe = distortion_partials_applied_jacobian(u, v, theta, e[:, 0], e[:, 1]).transpose(1, 2, 0)  # (2, 10, n)
    if not _all_columns(cols, pe.shape[1]):
        pe = pe[:, cols, :]
    return (_whiten(jc_inv, pe) if whitened else pe).transpose(2, 0, 1)


def _all_columns(cols: np.ndarray, k: int) -> bool:
    """Whether ``cols`` selects every one of ``k`` columns in order (then the selection is the array itself: no
    copy)."""
    return cols.size == k and bool(np.all(cols == np.arange(k)))


def observation_residuals(
    x_px: np.ndarray,
    y_px: np.ndarray,
    r: np.ndarray,
    attitude_obs: np.ndarray,
    theta: np.ndarray,
    s: np.ndarray | None = None,
) -> np.ndarray:
    """The residuals e of :func:`observation_terms` alone (no Jacobians): the cost of a trial step. ``s``: the
    rotated references C r (:func:`rotate`) when already computed."""
    q_u, q_v = ideal_offsets(x_px, y_px, theta)
    dx_u, dx_v, dy_u, dy_v = distortion_partials(x_px - theta[1], y_px - theta[2], theta)
    _, p, _ = _projection(r, attitude_obs, theta[0], s)
    det = (1 - dx_u) * (1 - dy_v) - dx_v * dy_u
    d0, d1 = q_u - p[:, 0], q_v - p[:, 1]
    return np.stack([((1 - dy_v) * d0 + dx_v * d1) / det, (dy_u * d0 + (1 - dx_u) * d1) / det], axis=1)


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


def residuals(
    data: CalibrationData, theta: np.ndarray, attitudes: np.ndarray, chunk_obs: int = DEFAULT_CHUNK_OBS
) -> np.ndarray:
    """Whitened residuals e (N, 2) [measured px] of every star (see :func:`observation_terms`)."""
    out = np.zeros((data.n_obs, 2))
    starts, counts = data.frame_starts, data.counts
    for f0, f1 in frame_chunks(starts, chunk_obs):
        a, b = int(starts[f0]), int(starts[f1])
        att = np.repeat(attitudes[f0:f1], counts[f0:f1], axis=0)
        out[a:b] = observation_residuals(data.x_px[a:b], data.y_px[a:b], data.r[a:b], att, theta)
    return out


def reduced_normal(blocks: NormalBlocks, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Schur complement over the attitude blocks, with Marquardt damping (diag scaled by 1 + damping).

    Returns (S, rhs, W) with S dtheta = rhs and W = B A^-1 (M, K, 3) for the back substitution."""
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


def initial_attitudes(data: CalibrationData, theta: np.ndarray) -> np.ndarray:
    """Per-frame least-squares attitude from the measured directions of the given camera (Markley's rotation,
    :func:`hostlink.calibration.frames.wahba_attitudes`)."""
    return wahba_attitudes(measured_directions(data, theta), data.r, data.frame_starts)


#: A trial step below this many standard deviations asks its pass for the final sums as well (``fit_round``): from
#: a step s the next one is ~1.5e-3 s^2 sigma here (superlinear Gauss-Newton: 10.3 -> 0.154 sigma at 10^4 frames),
#: so after a step below 15 sigma the pass most likely ends the round (``BundleOptions.step_tol`` or
#: ``remainder_tol``); the final sums cost ~25 % of a pass when they are not used, a separate final pass 100 %.
FINAL_STEP_SIGMAS = 15.0
#: The contraction (ratio of a step to the step before it, both undamped, on the same data and scale) must be below
#: this for ``BundleOptions.remainder_tol`` to end a round: a ratio near 1 is not a converging sequence.
CONTRACTION_MAX = 0.5
#: Gauss-Newton steps of each frame's attitude at a fixed camera, from the closed-form TRIAD start
#: (:func:`frame_attitudes`): the start is within ~2e-4 rad (centroid noise over the lever arm of one star) and one
#: step of this nearly linear 3-parameter problem squares the error (to ~1e-8 rad, 1e-3 of the attitude noise). The
#: camera step does not depend on what is left to first order (the Schur right-hand side carries g_phi), and the
#: cost only to second order (~1e-9 px^2 per frame).
ATTITUDE_STEPS = 1
#: A robust-scale round ends when the robust sigma of its residuals is within this fraction of the scale its Huber
#: weights used: a 1 % different scale moves the Huber threshold (3 sigma) by 0.03 sigma, which changes the weight
#: of ~0.1 % of the stars slightly and the estimate by far less than 0.01 sigma.
SCALE_ROUND_TOL = 0.01
#: The first round (plain least squares, before any robust scale is known) stops at steps below this many standard
#: deviations: the robust rounds after it continue from there to ``BundleOptions.step_tol``.
ROUGH_STEP_SIGMAS = 0.1
#: A warm-start sample's rounds (``bundle_adjust_chunks``) stop at steps below this many of the sample's own
#: standard deviations: the minimum of the next, ~10x larger level lies ~3 of them away (sampling: the sqrt(10)
#: parameters' share of the frames left out), and what a step of s leaves (~1.5e-3 s^2) is far below that, so
#: converging a sample further only costs passes; the next level's first step absorbs the difference.
WARM_STEP_SIGMAS = 2.0
#: A step below this many standard deviations that does not lower the cost ends the round as converged (the cost
#: then moves by less than the attitudes' own convergence changes it: ~1e-4 sigma^2 per frame), rather than being
#: retried at growing damping.
SMALL_STEP_SIGMAS = 0.01
#: Relative rounding of a pass's cost (a sum of ~10^4..10^7 terms in float64): a step whose cost is higher by less
#: than this is at the minimum and is accepted (its relative decrease, below ``ftol``, then ends the round).
COST_ROUNDING = 1e-12
#: Histogram of residual lengths for the robust scale: log-spaced bins over [1e-6, 1e3] px. Integer counts add up
#: exactly over chunks and workers, so the scale does not depend on how the frames are split; the median is
#: interpolated within a bin 0.25 % wide (the scale is used only for Huber weights and the 5-sigma gate).
SCALE_HIST_RANGE_PX = (1e-6, 1e3)
SCALE_HIST_BINS = 8192


def residual_histogram(norm_px: np.ndarray) -> np.ndarray:
    """Counts (SCALE_HIST_BINS,) of residual lengths [px] in the log-spaced bins of :data:`SCALE_HIST_RANGE_PX`
    (values outside go to the end bins)."""
    lo, hi = np.log(SCALE_HIST_RANGE_PX[0]), np.log(SCALE_HIST_RANGE_PX[1])
    pos = (np.log(np.maximum(norm_px, 1e-300)) - lo) * (SCALE_HIST_BINS / (hi - lo))
    idx = np.clip(pos.astype(np.int64), 0, SCALE_HIST_BINS - 1)
    return np.bincount(idx, minlength=SCALE_HIST_BINS).astype(np.int64)


def robust_sigma_from_histogram(hist: np.ndarray) -> float:
    """Per-axis sigma [px] from a :func:`residual_histogram`: its median (log-interpolated within the bin) over
    sqrt(2 ln 2), as :func:`hostlink.calibration.robust.robust_sigma_2d` does with the exact median."""
    n = int(hist.sum())
    if n == 0:
        return float("nan")
    cum = np.cumsum(hist)
    half = 0.5 * n
    k = int(np.searchsorted(cum, half, side="left"))
    below = cum[k] - hist[k]
    frac = (half - below) / max(hist[k], 1)
    lo, hi = np.log(SCALE_HIST_RANGE_PX[0]), np.log(SCALE_HIST_RANGE_PX[1])
    width = (hi - lo) / SCALE_HIST_BINS
    return float(np.exp(lo + (k + frac) * width) / RAYLEIGH_MEDIAN)


ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi


def angle_arcsec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle [arcsec] between unit vectors a and b (N, 3), from the chord: 2 arcsin(|a - b| / 2) (accurate at any
    angle, unlike arccos near 0); the chord's length by :func:`hostlink.calibration.frames.vector_norms`."""
    return 2.0 * np.arcsin(np.clip(vector_norms(a - b) / 2.0, 0.0, 1.0)) * ARCSEC_PER_RAD


def _lengths(e: np.ndarray) -> np.ndarray:
    """|e| of residuals (n, 2): np.linalg.norm(e, axis=1)'s numbers without its per-call overhead."""
    return np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1])


def _weights(norm: np.ndarray, sigma_px: float, huber_k: float) -> np.ndarray:
    return np.ones_like(norm) if not np.isfinite(sigma_px) else huber_weights(norm, sigma_px, huber_k)


def frame_attitudes(
    data: CalibrationData,
    theta: np.ndarray,
    sigma_px: float = np.inf,
    huber_k: float = 3.0,
    cam: CameraTerms | None = None,
) -> np.ndarray:
    """The attitude of every frame (M, 3, 3) that minimises its robust whitened cost at the camera ``theta``:
    TRIAD from the measured directions (:func:`hostlink.calibration.frames.triad_attitudes`), then
    :data:`ATTITUDE_STEPS` Gauss-Newton steps with the Huber
    weights of scale ``sigma_px`` (inf: plain least squares). A function of each frame alone, so the same for any
    split of the frames into chunks. With the attitudes eliminated this way the camera is fitted on the reduced
    cost sum_f min_C_f rho(e_f) (variable projection, Golub and Pereyra 1973), whose Gauss-Newton matrix is the Schur
    complement of :func:`reduced_normal`. ``cam``: the stars' :func:`camera_terms` at ``theta`` when already
    computed (the directions are then (q, F) normalised, the same numbers as ``measured_directions``)."""
    b = measured_directions(data, theta) if cam is None else offsets_to_unit(cam.q[:, 0], cam.q[:, 1], theta[0])
    att = triad_attitudes(b, data.r, data.frame_starts)
    for _ in range(ATTITUDE_STEPS):
        att_obs = np.repeat(att, data.counts, axis=0)
        e, jp = attitude_terms(data.x_px, data.y_px, data.r, att_obs, theta, cam)
        w = _weights(_lengths(e), sigma_px, huber_k)
        a, g = attitude_normal(e, jp, w, data.frame_starts)
        step = np.einsum("mij,mj->mi", inverse_3x3(a), g)
        att = apply_attitude_increment(att, -step)
    return att


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


@dataclass
class PassSums:
    """What one pass over the frames adds up; every field is a sum (or a max, or a union) over frames, so chunks
    and workers merge in any grouping (:meth:`merge`) to the same numbers up to the order of floating additions."""

    s: np.ndarray  # (K, K) reduced normal matrix (Schur complement), scaled camera columns
    rhs: np.ndarray  # (K,) its right-hand side
    u_diag: np.ndarray  # (K,) diagonal of U before the attitudes are eliminated
    cost: float  # robust cost at the pass's camera
    sum_e2: float  # sum |e|^2 [px^2]
    n_obs: int
    n_frames: int
    hist: np.ndarray  # residual_histogram of |e|
    over_gate: np.ndarray  # source rows whose |e| exceeds the gate given to the pass (int64)
    max_e_px: float = 0.0
    s_unit: np.ndarray | None = None  # final pass: S with unit weights, unscaled columns (the covariance)
    u_diag_unit: np.ndarray | None = None
    #: final pass: the (non-final) sums of the same pass without the stars in ``over_gate`` (and the frames they
    #: leave with fewer than three stars), i.e. the pass that starts the next round after gating, without a pass
    regated: PassSums | None = None
    #: final pass: sum and maximum of the squared / largest angle [arcsec] between each star's measured direction
    #: and its attitude-rotated reference (the report's residuals in arcsec, ``report.residual_sums``)
    sum_arcsec2: float = 0.0
    max_arcsec: float = 0.0

    def merge(self, other: PassSums) -> PassSums:
        def add(a, b):
            return None if a is None or b is None else a + b

        regated = None if self.regated is None or other.regated is None else self.regated.merge(other.regated)

        return PassSums(
            self.s + other.s,
            self.rhs + other.rhs,
            self.u_diag + other.u_diag,
            self.cost + other.cost,
            self.sum_e2 + other.sum_e2,
            self.n_obs + other.n_obs,
            self.n_frames + other.n_frames,
            self.hist + other.hist,
            np.concatenate([self.over_gate, other.over_gate]),
            max(self.max_e_px, other.max_e_px),
            add(self.s_unit, other.s_unit),
            add(self.u_diag_unit, other.u_diag_unit),
            regated,
            self.sum_arcsec2 + other.sum_arcsec2,
            max(self.max_arcsec, other.max_arcsec),
        )


def empty_pass(k: int, final: bool = False, regated: bool = True) -> PassSums:
    """Zero sums of K camera columns; ``final``: with the unit-weight sums and (``regated``) the sums without the
    gated stars, themselves final ones (:func:`chunk_pass`)."""
    z = np.zeros(0, dtype=np.int64)
    after = empty_pass(k, True, False) if regated else None
    unit = (np.zeros((k, k)), np.zeros(k), after) if final else (None, None, None)
    return PassSums(
        np.zeros((k, k)), np.zeros(k), np.zeros(k), 0.0, 0.0, 0, 0, np.zeros(SCALE_HIST_BINS, np.int64), z, 0.0, *unit
    )


def frames_of(data: CalibrationData, f0: int, f1: int) -> CalibrationData:
    """The frames [f0, f1) of ``data`` as a CalibrationData of their own (views, no copy)."""
    a, b = int(data.frame_starts[f0]), int(data.frame_starts[f1])
    return CalibrationData(
        data.x_px[a:b],
        data.y_px[a:b],
        data.r[a:b],
        data.frame_starts[f0 : f1 + 1] - a,
        data.frame_number[f0:f1],
        data.star_id[a:b],
        data.source_rows()[a:b],
    )


def without_rows(data: CalibrationData, excluded_rows: np.ndarray) -> CalibrationData:
    """``data`` less the stars whose source row is in the sorted array ``excluded_rows``, and less the frames left
    with fewer than :data:`hostlink.calibration.data.MIN_STARS_PER_FRAME` stars."""
    rows = data.source_rows()
    keep = None
    if excluded_rows.size:
        pos = np.minimum(np.searchsorted(excluded_rows, rows), excluded_rows.size - 1)
        keep = excluded_rows[pos] != rows
        if np.all(keep):
            keep = None
    if keep is None and np.all(data.counts >= MIN_STARS_PER_FRAME):
        return data  # nothing to leave out: the data themselves, not a copy (callers only read them)
    return data.select(np.ones(data.n_obs, dtype=bool) if keep is None else keep)[0]


@dataclass(frozen=True)
class PassRequest:
    """One pass over the frames: the camera, the scale of the Huber weights (inf: none), the columns and their
    scales, and what to leave out. ``final``: also the normal matrix with unit weights and unscaled columns (the
    covariance), and the stars beyond ``gate_px`` listed."""

    theta: np.ndarray
    sigma_px: float
    cols: np.ndarray
    col_scale: np.ndarray
    excluded_rows: np.ndarray
    huber_k: float
    chunk_obs: int
    final: bool = False
    gate_px: float = np.inf


def chunk_pass(data: CalibrationData, req: PassRequest) -> PassSums:
    """The sums of one chunk of frames (whole frames) for ``req``: per sub-chunk of at most ``chunk_obs`` stars,
    attitudes eliminated (:func:`frame_attitudes`), residuals and Jacobians (:func:`observation_terms`), Huber
    weights, normal blocks (:func:`normal_blocks`) reduced at once by the Schur complement
    (:func:`reduced_normal`), robust cost and residual histogram."""
    out = empty_pass(req.cols.size, req.final)
    for f0, f1 in frame_chunks(data.frame_starts, req.chunk_obs):
        sub = without_rows(frames_of(data, f0, f1), req.excluded_rows)
        if sub.n_frames == 0:
            continue
        frame_sums: list = []
        part = _checked_sums(sub, req, frame_sums)
        if part is None:
            out.cost = np.inf  # a camera some frame cannot be fitted with: the step is rejected
            return out
        if req.final:
            # the next round's first pass, after gating, for this sub-chunk: the same sums when no star of it is
            # beyond the gate, else those sums with the frames of the gated stars summed again without them (what
            # that pass computes, to the rounding of the sums). It is a final pass too (unit-weight sums, stars
            # beyond the same gate): when the next round's first step is already below the tolerance, it ends that
            # round without a pass of its own
            part.regated = replace(part) if part.over_gate.size == 0 else _regated(sub, part, frame_sums[0], req)
        out = out.merge(part)
    return out


def _regated(sub: CalibrationData, part: PassSums, frame_sums: np.ndarray, req: PassRequest) -> PassSums:
    """The final sums ``part`` of the sub-chunk ``sub`` without its stars beyond the gate (``part.over_gate``), their
    frames' attitudes fitted anew and the frames left with fewer than three stars dropped, as a pass without them
    gives them: only the frames holding those stars are summed again (with and without them). The matrices take out
    the first and add the second sums; the residuals' sums and maxima add the other frames' own (``frame_sums``, of
    :func:`_sub_chunk_sums`: no difference of large sums when a gated star's residual is huge) to the new ones.
    A frame that cannot be summed again makes the cost infinite (the step is rejected), as in a pass."""
    k = req.cols.size
    gated = np.sort(part.over_gate)
    rows = sub.source_rows()
    hit = gated[np.minimum(np.searchsorted(gated, rows), gated.size - 1)] == rows
    affected = np.unique(sub.frame_index()[hit])
    frames = take_frames(sub, affected)
    before = _checked_sums(frames, req)
    left = without_rows(frames, gated)
    after = _checked_sums(left, req) if left.n_frames else empty_pass(k, True, False)
    if before is None or after is None:
        failed = empty_pass(k, True, False)
        failed.cost = np.inf
        return failed
    others = np.ones(sub.n_frames, dtype=bool)
    others[affected] = False
    max_e, max_arcsec, sum_e2, sum_arcsec2, cost = frame_sums[:, others]
    return PassSums(
        part.s - before.s + after.s,
        part.rhs - before.rhs + after.rhs,
        part.u_diag - before.u_diag + after.u_diag,
        float(np.sum(cost)) + after.cost,
        float(np.sum(sum_e2)) + after.sum_e2,
        part.n_obs - before.n_obs + after.n_obs,
        part.n_frames - before.n_frames + after.n_frames,
        part.hist - before.hist + after.hist,
        after.over_gate,
        max(float(max_e.max(initial=0.0)), after.max_e_px),
        part.s_unit - before.s_unit + after.s_unit,
        part.u_diag_unit - before.u_diag_unit + after.u_diag_unit,
        None,
        float(np.sum(sum_arcsec2)) + after.sum_arcsec2,
        max(float(max_arcsec.max(initial=0.0)), after.max_arcsec),
    )


def _checked_sums(sub: CalibrationData, req: PassRequest, frame_sums: list | None = None) -> PassSums | None:
    """:func:`_sub_chunk_sums`, or None when some frame's terms are not finite at the request's camera."""
    try:
        with np.errstate(all="ignore"):  # a trial camera far off can make a frame's terms non-finite
            part = _sub_chunk_sums(sub, req, frame_sums)
    except np.linalg.LinAlgError:
        return None
    return part if np.isfinite(part.cost) and np.all(np.isfinite(part.s)) else None


def _sub_chunk_sums(sub: CalibrationData, req: PassRequest, frame_sums: list | None = None) -> PassSums:
    """The sums of :func:`chunk_pass` for the sub-chunk ``sub``. A final request appends to ``frame_sums`` (when
    given) each frame's largest |e| and arcsec angle, and its sums of |e|^2, of the squared angles and of the robust
    cost, (5, M) (:func:`_regated`)."""
    cam = camera_terms(sub.x_px, sub.y_px, req.theta)
    att = frame_attitudes(sub, req.theta, req.sigma_px, req.huber_k, cam)
    att_obs = np.repeat(att, sub.counts, axis=0)
    e, jt, jp = observation_terms(sub.x_px, sub.y_px, sub.r, att_obs, req.theta, req.cols, cam)
    norm = _lengths(e)
    w = _weights(norm, req.sigma_px, req.huber_k)
    rho = huber_rho(norm, req.sigma_px, req.huber_k)
    blocks = NormalBlocks(*normal_blocks(e, jt, jp, w, sub.frame_starts, req.col_scale), e)
    s, rhs, _ = reduced_normal(blocks, 0.0)
    unit, arcsec = (None, None), (0.0, 0.0)
    if req.final:
        s_unit, u_diag_unit = unit_weight_normal(blocks, s, jt, jp, w, sub.frame_starts, req.col_scale)
        unit = (s_unit / np.outer(req.col_scale, req.col_scale), u_diag_unit / req.col_scale**2)  # unscaled columns
        b = offsets_to_unit(cam.q[:, 0], cam.q[:, 1], req.theta[0])
        ang = angle_arcsec(b, rotate(att_obs, sub.r))
        arcsec = (float(np.sum(ang * ang)), float(ang.max(initial=0.0)))
        if frame_sums is not None:
            starts = sub.frame_starts[:-1]
            per_frame = [np.maximum.reduceat(norm, starts), np.maximum.reduceat(ang, starts)]
            per_frame += [np.add.reduceat(x, starts) for x in (norm * norm, ang * ang, rho)]
            frame_sums.append(np.stack(per_frame))
    return PassSums(
        s,
        rhs,
        np.diag(blocks.u).copy(),
        float(np.sum(rho)),
        float(np.sum(norm * norm)),
        sub.n_obs,
        sub.n_frames,
        residual_histogram(norm),
        sub.source_rows()[norm > req.gate_px].astype(np.int64),
        float(norm.max(initial=0.0)),
        *unit,
        None,
        *arcsec,
    )


@dataclass(frozen=True)
class ChunkSource:
    """The frames of a calibration as chunks (whole frames, each with its source rows): ``handles`` are what
    ``load`` turns into a :class:`CalibrationData` (the data itself in memory, a spool file on disk), so a pass
    can run where the handle is (:mod:`hostlink.calibration.distributed`)."""

    handles: tuple
    load: Callable[[object], CalibrationData] | None = None
    #: the number of frames of a handle's chunk without loading all of it (None: load the chunk and count)
    count: Callable[[object], int] | None = None
    #: the chunk loaded last, kept until another one is loaded (memory: one chunk), so the passes over a session of
    #: one chunk read it once (the chunks are read-only: every pass selects copies)
    _last: list = field(default_factory=list, compare=False, repr=False)

    def chunk(self, handle: object) -> CalibrationData:
        if self.load is None:
            return handle
        if self._last and self._last[0] == handle:
            return self._last[1]
        self._last.clear()  # the previous chunk is released before the next one is read
        data = self.load(handle)
        self._last.extend((handle, data))
        return data

    def n_frames(self) -> int:
        """Frames in all the chunks."""
        if self.load is None:
            return sum(h.n_frames for h in self.handles)
        return sum(self.count(h) if self.count is not None else self.load(h).n_frames for h in self.handles)

    def __iter__(self):
        return (self.chunk(h) for h in self.handles)


def in_memory_source(data: CalibrationData) -> ChunkSource:
    """``data`` as a one-chunk source (the in-memory path: the same passes, one chunk)."""
    return ChunkSource((data,))


def serial_pass(source: ChunkSource, req: PassRequest) -> PassSums:
    """Run :func:`chunk_pass` over every chunk in this process, one chunk in memory at a time, in order."""
    out = empty_pass(req.cols.size, req.final)
    for chunk in source:
        out = out.merge(chunk_pass(chunk, req))
    return out


#: A pass runner: (source, request) -> sums over all chunks. :func:`serial_pass`, or a Dask one.
PassRunner = Callable[[ChunkSource, PassRequest], PassSums]


#: Geodesic acceleration of a Gauss-Newton step over the full data (:func:`step_acceleration`) for steps above this
#: many standard deviations (below, what the second-order term leaves is below ~0.01 sigma and the contraction test
#: ends the fit on it anyway).
ACCELERATION_MIN_SIGMAS = 1.0
#: The acceleration is used only while 2 |a| / |v| (in the camera's standard deviations) is at most this: Transtrum
#: and Sethna's bound (2012, sec. 3.2), beyond which the second-order model of the step is not to be trusted.
ACCELERATION_MAX_RATIO = 0.75
#: The step fraction h of the second difference (r(+h v) - 2 r(0) + r(-h v)) / h^2 along the step: exact for the
#: quadratic term, the quartic one entering as h^2 / 12 of it.
ACCELERATION_H = 0.5


def step_acceleration(
    sample: CalibrationData,
    theta: np.ndarray,
    dx: np.ndarray,
    cols: np.ndarray,
    col_scale: np.ndarray,
    sigma_px: float,
    huber_k: float,
    s_full: np.ndarray,
    n_obs_full: int,
) -> np.ndarray | None:
    """The geodesic acceleration a (scaled columns) of the Gauss-Newton step ``dx`` of the full data at the camera
    ``theta`` (Transtrum and Sethna 2012, "Improvements to the Levenberg-Marquardt algorithm for nonlinear
    least-squares minimization", eq. 15: a = -(J^T W J)^-1 J^T W r''; the step taken is dx + a / 2), its
    second-order term measured on ``sample`` (frames of the same session held in memory): the second directional
    derivative r'' of each star's residual along the joint step (the camera's ``dx`` and each frame's attitude step
    that goes with it, -A^-1 (B^T dx + g_phi)) by the central second difference at :data:`ACCELERATION_H`, which is
    free of the centroid noise (it cancels); J^T W r'' reduced over the sample's attitudes (Schur complement) and
    scaled to the full data by their ratio of stars, then solved with the full data's reduced matrix ``s_full``.

    What it corrects: a principal point d px off is compensated by every frame's attitude, whose rotation adds a
    second-order change of scale, ~0.9 d^2 / F (measured: the focal length a Gauss-Newton step leaves), and the
    distortion's curvature in the principal point adds its own; along the weak principal-point direction these are
    several tenths of the camera's standard deviation. At 10^4 frames, one step from a principal point (2, -1) px
    off leaves 0.49 sigma, the accelerated one 0.041 from a 100-frame sample (0.028 from 1000 frames or from all).
    None when the sample's terms are not finite."""
    with np.errstate(all="ignore"):
        att = frame_attitudes(sample, theta, sigma_px, huber_k)
        e0 = residuals(sample, theta, att)
        w = _weights(_lengths(e0), sigma_px, huber_k)
        blocks = accumulate_normals(sample, theta, att, cols, w, col_scale)
        try:
            _, _, a_inv = reduced_normal(blocks)
        except np.linalg.LinAlgError:
            return None
        dphi = -np.einsum("mij,mj->mi", a_inv, np.einsum("mkj,k->mj", blocks.b, dx) + blocks.g_phi)

        def moved(h: float) -> np.ndarray:
            camera = theta.copy()
            camera[cols] += h * dx * col_scale
            return residuals(sample, camera, apply_attitude_increment(att, h * dphi))

        h = ACCELERATION_H
        r2 = (moved(h) - 2.0 * e0 + moved(-h)) / (h * h)
        curvature = accumulate_normals(sample, theta, att, cols, w, col_scale, values=r2)
        _, rhs, _ = reduced_normal(replace(blocks, g=curvature.g, g_phi=curvature.g_phi))
        accel = solve_scaled(s_full, rhs * (n_obs_full / max(sample.n_obs, 1)))
    return accel if np.all(np.isfinite(accel)) else None


@dataclass
class ChunkedBundleResult:
    """The camera of :func:`bundle_adjust_chunks` and what the report needs; no per-frame state."""

    theta: np.ndarray
    estimate: tuple[str, ...]
    normal: np.ndarray
    normal_u_diag: np.ndarray
    covariance: np.ndarray
    sigma_px: float
    sigma_estimated_px: float
    robust_sigma_px: float
    gated_rows: np.ndarray  # source rows dropped by residual gating (sorted int64)
    n_obs: int
    n_frames: int
    max_e_px: float
    history: list[dict] = field(default_factory=list)
    converged: bool = False
    #: the residual sums of the final pass (``report.residual_sums``' keys), at the camera of that pass: ``theta``
    #: less the last step, below ``BundleOptions.step_tol`` or ``remainder_tol`` standard deviations
    residual_sums: dict = field(default_factory=dict)


def bundle_adjust_chunks(
    source: ChunkSource,
    nominal: CameraParams,
    options: BundleOptions | None = None,
    excluded_rows: np.ndarray | None = None,
    run_pass: PassRunner = serial_pass,
    warm_start: tuple[CalibrationData, ...] = (),
) -> ChunkedBundleResult:
    """Calibrate the camera over the chunks of ``source``, leaving out the stars whose source rows are in
    ``excluded_rows`` (interstar voting's rejects), with one pass over the chunks per Levenberg-Marquardt
    iteration: memory O(K^2 + one chunk) for any number of frames.

    Each pass eliminates every frame's attitude at the pass's camera (:func:`frame_attitudes`) and sums the reduced
    normal equations (Schur complement) with Huber weights of a fixed robust scale. The first round is plain least
    squares to :data:`ROUGH_STEP_SIGMAS` (on ``warm_start``'s first sample of the frames held in memory, when given,
    to :data:`WARM_STEP_SIGMAS`; each further, larger sample then continues at that sample's robust scale to the
    same tolerance, so the full data
    start within a few of their own standard deviations: ~10x more frames per level). A round converges at a step
    below ``options.step_tol`` sigma, or one whose product with the measured contraction is below
    ``options.remainder_tol`` sigma (the step is applied), and ends with a final pass (also unit weights: the
    covariance; the stars beyond ``options.gate`` robust sigmas; the sums without them; the residuals the report
    gives as ``after``): the last trial pass when its step was below :data:`FINAL_STEP_SIGMAS` (it was asked for
    them), else a pass of its own. Stars gated, the next round starts from the final pass's sums without them (final
    sums too: a first step already small enough ends that round on them); the fit ends when no star was gated and
    the scale moved by at most :data:`SCALE_ROUND_TOL`. A step of the full data above :data:`ACCELERATION_MIN_SIGMAS`
    is taken with its geodesic acceleration (:func:`step_acceleration`, on the first warm-start level), so that
    what the principal point's nonlinearity leaves does not cost a pass. Typically two passes over the frames after
    a warm start (the second a final one): measured on 20 sessions of 10^4 frames, 17 took two and 3 three (without
    the acceleration 4 took two, 16 three).
    ``options.screen`` is not used here (voting is the caller's: ``excluded_rows``). Raises ValueError when no frame
    with three stars is left."""
    opt = options or BundleOptions()
    cols = parameter_columns(opt.estimate)
    if cols.size == 0:
        raise ValueError("no parameter to estimate")
    scale = parameter_scales(nominal)[cols]
    theta = nominal.model_vector(np.float64)
    excluded = np.unique(np.asarray(excluded_rows if excluded_rows is not None else [], dtype=np.int64))
    gated = np.zeros(0, dtype=np.int64)
    history: list[dict] = []
    # the largest contraction measured between two undamped steps on the full data at a robust scale (None: none yet)
    state: dict = {"iteration": 0, "contraction": None}

    def request(th, sig, fin=False, gate_px=np.inf):
        drop = np.union1d(excluded, gated)
        return PassRequest(th, sig, cols, scale, drop, opt.huber_k, opt.chunk_obs, fin, gate_px)

    def fit_round(src, theta, cur, sigma, step_tol):
        """LM iterations at a fixed robust scale from ``cur`` (the pass at ``theta``); returns theta, the last
        pass, the camera of that pass (theta less the last, tiny step when converged) and whether it converged.
        A trial step below :data:`FINAL_STEP_SIGMAS` asks its pass for the final sums too (the covariance, the
        gate and the sums without the gated stars): the next step will most likely end the round, and that pass
        then serves as the round's final one."""
        # Gauss-Newton on the reduced cost, Marquardt's damping only after a step that fails; the first round
        # starts damped (from a nominal camera the full step can leave every star off the detector)
        damping = 1e-6 if not np.isfinite(sigma) else 0.0
        robust_full = bool(np.isfinite(sigma)) and src is source
        remainder_tol = opt.remainder_tol
        previous = None  # the last accepted step [sigma] when it was undamped (the contraction's denominator)
        while state["iteration"] < opt.max_iter:
            state["iteration"] += 1
            noise = max(robust_sigma_from_histogram(cur.hist), 1e-300)
            accepted = False
            for _trial in range(12):
                s = cur.s.copy()
                kdx = np.arange(s.shape[0])
                s[kdx, kdx] *= 1.0 + damping
                dx = solve_scaled(s, cur.rhs)
                # the step's size in standard deviations of the camera: sqrt(dx^T S dx) / sigma
                step_sigmas = float(np.sqrt(max(dx @ cur.rhs, 0.0))) / noise
                if src is source and damping == 0.0 and step_sigmas > ACCELERATION_MIN_SIGMAS and warm_start:
                    dx = accelerated(theta, dx, cur, sigma)
                theta_new = theta.copy()
                theta_new[cols] += dx * scale
                if step_sigmas < step_tol:
                    return theta_new, cur, theta, True  # converged: this last, tiny step is applied unevaluated
                if robust_full and damping == 0.0 and previous is not None:
                    ratio = step_sigmas / previous
                    state["contraction"] = max(state["contraction"] or 0.0, ratio)
                rate = state["contraction"]
                if robust_full and rate is not None and rate < CONTRACTION_MAX and rate * step_sigmas < remainder_tol:
                    return theta_new, cur, theta, True  # converged: what this step leaves is below remainder_tol
                ask_final = bool(np.isfinite(sigma)) and src is source and step_sigmas < FINAL_STEP_SIGMAS
                # the gate at the robust scale of the pass at theta (that of the pass itself is not known before it)
                new = run_pass(src, request(theta_new, sigma, ask_final, opt.gate * noise if ask_final else np.inf))
                # accepted when the cost does not rise beyond the rounding of its sum (a step at the minimum)
                if np.isfinite(new.cost) and new.cost <= cur.cost * (1.0 + COST_ROUNDING):
                    accepted = True
                    break
                if step_sigmas < SMALL_STEP_SIGMAS:
                    return theta, cur, theta, True  # a step this small that does not lower the cost: at the minimum
                damping = max(10.0 * damping, 1e-6)
            if not accepted:
                return theta, cur, theta, True  # no descent direction left at any damping: at the minimum
            decrease = (cur.cost - new.cost) / max(cur.cost, 1e-300)
            theta, cur = theta_new, new
            previous = step_sigmas if damping == 0.0 else None
            damping = damping / 10.0 if damping > 1e-12 else 0.0
            entry = {
                "iteration": state["iteration"],
                "cost": new.cost,
                "rms_px": float(np.sqrt(new.sum_e2 / max(new.n_obs, 1))),
                "robust_sigma_px": robust_sigma_from_histogram(new.hist),
                "damping": damping,
                "step_sigmas": step_sigmas,
                "n_obs": new.n_obs,
            }
            history.append(entry)
            if opt.progress:
                opt.progress(entry)
            if decrease < opt.ftol:
                return theta, cur, theta, True
        return theta, cur, theta, False

    def accelerated(theta, dx, cur, sigma):
        """``dx`` plus half its geodesic acceleration (:func:`step_acceleration`, measured on the first warm-start
        level less the stars left out), when Transtrum and Sethna's bound admits it."""
        sample = without_rows(warm_start[0], np.union1d(excluded, gated))
        if sample.n_frames == 0:
            return dx
        accel = step_acceleration(sample, theta, dx, cols, scale, sigma, opt.huber_k, cur.s, cur.n_obs)
        if accel is None:
            return dx
        size = np.sqrt(max(accel @ cur.s @ accel, 0.0) / max(dx @ cur.s @ dx, 1e-300))
        return dx + 0.5 * accel if 2.0 * size <= ACCELERATION_MAX_RATIO else dx

    def check(p: PassSums, first: bool) -> PassSums:
        if p.n_frames == 0 or not np.isfinite(p.cost):
            raise ValueError(
                "no frame with at least 3 consistent identified stars"
                if first
                else "every frame lost its stars to outlier gating"
            )
        return p

    sigma = np.inf  # the first round: plain least squares
    for level in warm_start:
        warm = in_memory_source(level)
        cur = check(run_pass(warm, request(theta, sigma)), True)
        theta, cur, _, _ = fit_round(warm, theta, cur, sigma, WARM_STEP_SIGMAS)
        sigma = robust_sigma_from_histogram(cur.hist)
    cur = check(run_pass(source, request(theta, sigma)), True)
    final = None
    converged = False
    for _round in range(opt.max_gate_rounds + 3):
        step_tol = opt.step_tol if np.isfinite(sigma) else ROUGH_STEP_SIGMAS
        theta, last, theta_last, converged = fit_round(source, theta, cur, sigma, step_tol)
        sigma_new = robust_sigma_from_histogram(last.hist)
        if last.s_unit is not None:  # the round's last pass was also its final one (at the round's scale)
            final, final_theta, final_scale = last, theta_last, sigma
        else:
            final = check(run_pass(source, request(theta, sigma_new, True, opt.gate * sigma_new)), False)
            final_theta, final_scale = theta, sigma_new
        newly = np.setdiff1d(final.over_gate, gated)
        stable = np.isfinite(sigma) and abs(sigma_new / sigma - 1.0) <= SCALE_ROUND_TOL
        if newly.size and _round < opt.max_gate_rounds:
            gated = np.union1d(gated, newly)
            # the final pass's sums without the gated stars: the next round's first pass, without a pass (a final
            # pass that was itself such sums has none: then a pass)
            again = final.regated or run_pass(source, request(final_theta, final_scale))
            theta, cur, sigma = final_theta, check(again, False), final_scale
            continue
        if stable or not converged or state["iteration"] >= opt.max_iter:
            break
        # the next round at the new scale starts from the final pass when it was made at that scale
        cur = final if final_scale == sigma_new else check(run_pass(source, request(theta, sigma_new)), False)
        sigma = sigma_new
    assert final is not None
    dof = max(2 * final.n_obs - cols.size - 3 * final.n_frames, 1)
    sigma_est = float(np.sqrt(final.sum_e2 / dof))
    sigma_used = float(opt.noise_px) if opt.noise_px else sigma_est
    return ChunkedBundleResult(
        theta=theta,
        estimate=tuple(ESTIMATE_NAMES[c] for c in cols),
        normal=final.s_unit,
        normal_u_diag=final.u_diag_unit,
        covariance=covariance_from_normal(final.s_unit, sigma_used),
        sigma_px=sigma_used,
        sigma_estimated_px=sigma_est,
        robust_sigma_px=robust_sigma_from_histogram(final.hist),
        gated_rows=gated,
        n_obs=final.n_obs,
        n_frames=final.n_frames,
        max_e_px=final.max_e_px,
        history=history,
        converged=converged,
        residual_sums={
            "sum_px2": final.sum_e2,
            "max_px": final.max_e_px,
            "sum_arcsec2": final.sum_arcsec2,
            "max_arcsec": final.max_arcsec,
            "n_stars": final.n_obs,
            "n_frames": final.n_frames,
        },
    )


def bundle_adjust(data: CalibrationData, nominal: CameraParams, options: BundleOptions | None = None) -> BundleResult:
    """Calibrate the camera and every frame's attitude by robust Levenberg-Marquardt: :func:`bundle_adjust_chunks`
    on ``data`` as one chunk (with interstar voting first when ``options.screen``), plus the in-memory extras:
    the inlier data, their attitudes and the masks of input rows used and gated.

    ``nominal`` gives the starting values and the fixed values of parameters not in ``options.estimate``.
    Raises ValueError if fewer than one frame with three consistent stars remains.
    """
    opt = options or BundleOptions()
    theta0 = nominal.model_vector(np.float64)
    rows = data.source_rows()
    n_input = data.n_obs
    voted = np.zeros(n_input, dtype=bool)
    if opt.screen:
        voted = ~vote_consistent_stars(data, measured_directions(data, theta0))
    res = bundle_adjust_chunks(in_memory_source(data), nominal, opt, rows[voted])
    rows_gated = np.isin(rows, res.gated_rows)
    fit, rows_used, frame_kept = data.select(~voted & ~rows_gated)
    m_in = data.select(np.ones(n_input, dtype=bool))[0].n_frames
    return BundleResult(
        theta=res.theta,
        attitudes=frame_attitudes(fit, res.theta, res.robust_sigma_px, opt.huber_k),
        data=fit,
        rows_used=rows_used,
        rows_gated=rows_gated,
        n_rejected_voting=int(voted.sum()),
        n_rejected_gating=int(rows_gated.sum()),
        n_frames_dropped=int(m_in - fit.n_frames),
        sigma_px=res.sigma_px,
        sigma_estimated_px=res.sigma_estimated_px,
        estimate=res.estimate,
        normal=res.normal,
        normal_u_diag=res.normal_u_diag,
        covariance=res.covariance,
        history=res.history,
        converged=res.converged,
    )


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
