"""The measurement model of the bundle adjustment: projection, whitening, residuals and their Jacobians.

Per identified star k of frame f (docs/camera-model.md):

    q(x_k, y_k; theta) = F (C_f r_k)_xy / (C_f r_k)_z

with q the ideal offsets of the measured centroid (``onboard.camera.ideal_offset_jacobians``), F = theta[0] in
pixels and C_f the attitude (b = C r). The residual is whitened into measured pixels,

    e_k = Jc_k^-1 (q_k - p_k),     Jc = dq/d(x, y),

so that isotropic centroid noise sigma gives e_k ~ N(0, sigma^2 I) to first order, and least squares is maximum
likelihood. Unknowns: the selected camera parameters and a 3-parameter rotation increment per frame
(C <- exp(-[dphi x]) C). Everything here is a function of a block of stars; the sums over them are
:mod:`hostlink.calibration.normal`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks
from hostlink.calibration.frames import vector_norms
from onboard.camera import (
    distortion_partials,
    distortion_partials_applied_jacobian,
    ideal_offset_jacobians,
    ideal_offsets,
)
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Most stars processed at once in a pass over the data: bounds the working arrays (~1.5 kB per star, ~8 MB per pass).
#: Small enough that each temporary (~1 MB) stays in cache and is reused by the allocator rather than mapped afresh
#: and page-faulted in, large enough that numpy's per-call overhead stays small (the timings behind the choice:
#: docs/calibration.md).
DEFAULT_CHUNK_OBS = 5_000


def parameter_columns(estimate: tuple[str, ...]) -> np.ndarray:
    """Indices into the model vector of the estimated parameters (ESTIMATE_NAMES order)."""
    unknown = [n for n in estimate if n not in ESTIMATE_NAMES]
    if unknown:
        raise ValueError(f"unknown parameter name(s) {', '.join(unknown)} (allowed: {','.join(ESTIMATE_NAMES)})")
    return np.array([ESTIMATE_NAMES.index(n) for n in ESTIMATE_NAMES if n in estimate], dtype=np.int64)


def half_diagonal_px(params: CameraParams) -> float:
    """The detector's half-diagonal [px], 0.5 hypot(width, height): the radius the model's scales and limits and the
    noise floor's field radius are measured in."""
    return 0.5 * float(np.hypot(*params.image_size_px))


def parameter_scales(params: CameraParams) -> np.ndarray:
    """Characteristic size of a unit change of each model-vector entry: 1 px for F, x0, y0 and 1 px of distortion
    at the detector half-diagonal R for the rest (k1 ~ R^-3, k2 ~ R^-5, k3 ~ R^-7, p and s ~ R^-2). Steps are
    solved in these units so the normal matrix is well scaled."""
    half_diag = half_diagonal_px(params)
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


ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi


def angle_arcsec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle [arcsec] between unit vectors a and b (N, 3), from the chord: 2 arcsin(|a - b| / 2) (accurate at any
    angle, unlike arccos near 0); the chord's length by :func:`hostlink.calibration.frames.vector_norms`."""
    return 2.0 * np.arcsin(np.clip(vector_norms(a - b) / 2.0, 0.0, 1.0)) * ARCSEC_PER_RAD


def whitened_by_noise(sigma_px: np.ndarray, e: np.ndarray, *jacobians: np.ndarray) -> tuple[np.ndarray, ...]:
    """The residuals e (n, 2) and Jacobians (n, 2, k) of stars of known centroid noise ``sigma_px`` (n,) [px], each
    star's divided by its sigma: unit-variance residuals, so least squares on them is maximum likelihood for
    stars of different noise (the per-star whitening of the measurement model; Huber weights, the robust scale and
    the gate then work on them, the fitted scale being the noise relative to the given one). The Jacobians stay
    stored entry by entry (:func:`observation_terms`' layout)."""
    inv = 1.0 / sigma_px
    out = [e * inv[:, None]]
    for j in jacobians:
        out.append((j.transpose(1, 2, 0) * inv).transpose(2, 0, 1))
    return tuple(out)


def residual_lengths(e: np.ndarray) -> np.ndarray:
    """|e| of residuals (n, 2): np.linalg.norm(e, axis=1)'s numbers without its per-call overhead."""
    return np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1])
