"""The one camera model (docs/camera-model.md), written once and dtype-generic.

Every function takes the model vector ``theta`` = (F_px, x0_px, y0_px, k1, k2, k3, p1, p2, s1, s2) as returned by
``CameraParams.model_vector(dtype)``, and computes in the dtype of its inputs: the sensor calls it with float32
arrays, the host with float64 ones. Nothing here promotes: constants are Python scalars (NEP 50 keeps the array
dtype) and no float64 array is created unless the caller passed float64.

Jacobians are with respect to the model vector (F in pixels). The focal length in millimetres is F p / 1000, so
d/df_mm = (1000 / p) d/dF_px.

Source: Weng, Cohen, Herniou (1992), as used in seed 000 eq. 7; pinhole direction as seed 004 eq. 2 / seed 000 eq. 2
with the sign convention of docs/camera-model.md (+x along increasing column, +y along increasing row, +z boresight).
"""

from __future__ import annotations

import numpy as np

#: Newton iterations for the simulator's inverse mapping; each roughly squares the error, 8 is far more than needed.
_INVERSE_MAX_ITER = 8


def distortion_px(u: np.ndarray, v: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weng distortion (dx, dy) at measured offsets (u, v) from the principal point [px] (seed 000 eq. 7)."""
    k1, k2, k3, p1, p2, s1, s2 = (theta[i] for i in range(3, 10))
    g1, g2, g3, g4 = s1 + p1, s2 + p2, p1 + p1, p2 + p2
    r2 = u * u + v * v
    radial = r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = (g1 + g3) * u * u + g4 * u * v + g1 * v * v + u * radial
    dy = g2 * u * u + g3 * u * v + (g2 + g4) * v * v + v * radial
    return dx, dy


def ideal_offsets(x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measured centroid -> ideal offsets (u', v') = (u - dx, v - dy) from the principal point [px]."""
    u = x_px - theta[1]
    v = y_px - theta[2]
    dx, dy = distortion_px(u, v, theta)
    return u - dx, v - dy


def offsets_to_unit(u_ideal: np.ndarray, v_ideal: np.ndarray, focal_px: np.ndarray) -> np.ndarray:
    """Ideal offsets -> sensor-frame unit vectors b = (u', v', F) / |.|, shape (N, 3)."""
    f = np.asarray(focal_px).astype(np.result_type(u_ideal), copy=False)
    dtype = np.result_type(u_ideal, v_ideal, f)
    dtype = dtype if np.issubdtype(dtype, np.floating) else np.dtype(np.float64)  # integer offsets: float64 out
    u, v, f = (np.asarray(a, dtype=dtype) for a in (u_ideal, v_ideal, f))
    # each component over the length sqrt((u'^2 + v'^2) + F^2), written out rather than a sum over a stacked axis
    # of three (the same numbers; numpy's reduction over so short an axis costs ten times the arithmetic)
    norm = np.sqrt(u * u + v * v + f * f)
    out = np.empty(np.broadcast_shapes(u.shape, v.shape, f.shape) + (3,), dtype=dtype)
    np.divide(u, norm, out=out[..., 0])
    np.divide(v, norm, out=out[..., 1])
    np.divide(f, norm, out=out[..., 2])
    return out


def pixels_to_unit(x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Measured centroids -> sensor-frame unit vectors, shape (N, 3). What a sensor evaluates every frame."""
    u_i, v_i = ideal_offsets(x_px, y_px, theta)
    return offsets_to_unit(u_i, v_i, theta[0])


def distortion_partials(u: np.ndarray, v: np.ndarray, theta: np.ndarray):
    """Partial derivatives of (dx, dy) with respect to (u, v): returns dx_u, dx_v, dy_u, dy_v."""
    k1, k2, k3, p1, p2, s1, s2 = (theta[i] for i in range(3, 10))
    two, three = theta.dtype.type(2), theta.dtype.type(3)  # typed constants: no float64 scalar on numpy 1.x either
    g1, g2, g3, g4 = s1 + p1, s2 + p2, p1 + p1, p2 + p2
    r2 = u * u + v * v
    radial = r2 * (k1 + r2 * (k2 + r2 * k3))
    radial_d = k1 + r2 * (two * k2 + three * k3 * r2)  # d radial / d r2
    dx_u = two * (g1 + g3) * u + g4 * v + radial + two * u * u * radial_d
    dx_v = g4 * u + two * g1 * v + two * u * v * radial_d
    dy_u = two * g2 * u + g3 * v + two * u * v * radial_d
    dy_v = g3 * u + two * (g2 + g4) * v + radial + two * v * v * radial_d
    return dx_u, dx_v, dy_u, dy_v


def distortion_partials_applied_jacobian(
    u: np.ndarray, v: np.ndarray, theta: np.ndarray, a: np.ndarray, b: np.ndarray
) -> np.ndarray:
    """d(P w)/d theta (N, 2, 10) for the matrix of distortion partials P = [[dx_u, dx_v], [dy_u, dy_v]]
    (:func:`distortion_partials`) applied to a vector w = (a, b) held fixed, at measured offsets (u, v) [px].

    The derivative of the whitening Jc^-1 = (I - P)^-1 of a residual: d(Jc^-1)/d theta_k d = Jc^-1 (dP/d theta_k) e
    with d = Jc e. P is linear in k1..s2, so those columns are P at the unit coefficient; the principal point enters
    through u = x - x0, v = y - y0, so d/dx0 = -d/du, d/dy0 = -d/dv (second derivatives of seed 000 eq. 7's
    distortion); F does not enter (zero column). Written out term by term, in the dtype of the inputs."""
    k1, k2, k3, p1, p2, s1, s2 = (theta[i] for i in range(3, 10))
    two, three, four, six = (theta.dtype.type(c) for c in (2, 3, 4, 6))
    g1, g2, g3, g4 = s1 + p1, s2 + p2, p1 + p1, p2 + p2
    # P w = radial w + 2 rd (u t, v t) + (the g terms), with t = u a + v b: every column is a few of these products
    ua, vb, va, ub = u * a, v * b, v * a, u * b
    t = ua + vb
    ut, vt = u * t, v * t
    r2 = u * u + v * v
    r4 = r2 * r2
    rd = k1 + r2 * (two * k2 + three * k3 * r2)  # d radial / d r2
    rdd = two * k2 + six * k3 * r2  # d^2 radial / d r2^2
    out = _by_entry(np.shape(u)[0], 10, np.result_type(u, a))
    # p1: g1 = 1, g3 = 2; p2: g2 = 1, g4 = 2; s1: g1 = 1; s2: g2 = 1
    t2 = two * t
    s2w = two * (va + ub)
    p1_row0 = t2 + four * ua  # 6 u a + 2 v b
    p2_row1 = t2 + four * vb  # 2 u a + 6 v b
    out[:, 0, 6] = p1_row0
    out[:, 1, 6] = s2w
    out[:, 0, 7] = s2w
    out[:, 1, 7] = p2_row1
    out[:, 0, 8] = t2
    out[:, 1, 9] = t2
    # principal point: -d(P w)/du and -d(P w)/dv, with d rd/du = 2 u rdd, d radial/du = 2 u rd, dt/du = a (same in
    # v, b): d(row 0)/du = rd (6 u a + 2 v b) + 4 u^2 rdd t, d(row 0)/dv = d(row 1)/du = 2 rd (v a + u b) + 4 u v rdd t,
    # d(row 1)/dv = rd (2 u a + 6 v b) + 4 v^2 rdd t, plus the g terms' constant derivatives
    q = four * rdd * t
    cross = rd * s2w + (u * v) * q
    out[:, 0, 1] = -(rd * p1_row0 + (u * u) * q + two * (g1 + g3) * a + g4 * b)
    out[:, 1, 1] = -(cross + two * g2 * a + g3 * b)
    out[:, 0, 2] = -(cross + g4 * a + two * g1 * b)
    out[:, 1, 2] = -(rd * p2_row1 + (v * v) * q + g3 * a + two * (g2 + g4) * b)
    # radial k1, k2, k3: radial = r2^n, 2 rd = 2 n r2^(n-1): rows radial a + 2 rd u t and radial b + 2 rd v t
    for col, radial, rd_n in ((3, r2, two), (4, r4, four * r2), (5, r4 * r2, six * r4)):
        out[:, 0, col] = radial * a + rd_n * ut
        out[:, 1, col] = radial * b + rd_n * vt
    return out


def _by_entry(n: int, k: int, dtype) -> np.ndarray:
    """Zeros of shape (n, 2, k) stored entry by entry: each (row, column) entry of the n Jacobians is contiguous
    (a transposed view of a (2, k, n) array), so each entry is written in one pass over contiguous memory and the
    host sums rows of them (``hostlink.calibration.bundle.normal_blocks``); indexing is as for any (n, 2, k) array."""
    return np.zeros((2, k, n), dtype=dtype).transpose(2, 0, 1)


def ideal_offset_jacobians(
    x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ideal offsets and their analytic Jacobians.

    Returns ``(q, J_theta, J_centroid)``: q (N, 2) = (u', v'); J_theta (N, 2, 10) = d(u', v')/d theta (the F
    column is zero: offsets do not depend on F); J_centroid (N, 2, 2) = d(u', v')/d(x, y).
    """
    u = x_px - theta[1]
    v = y_px - theta[2]
    dx, dy = distortion_px(u, v, theta)
    dx_u, dx_v, dy_u, dy_v = distortion_partials(u, v, theta)
    n = np.shape(u)[0]
    dtype = np.result_type(u)
    r2 = u * u + v * v
    j_theta = _by_entry(n, 10, dtype)
    # principal point: u = x - x0, so d/dx0 = -d/du
    j_theta[:, 0, 1] = -(1 - dx_u)
    j_theta[:, 0, 2] = dx_v
    j_theta[:, 1, 1] = dy_u
    j_theta[:, 1, 2] = -(1 - dy_v)
    # radial: u' = u - u (k1 r2 + k2 r2^2 + k3 r2^3)
    r4 = r2 * r2
    r6 = r4 * r2
    j_theta[:, 0, 3], j_theta[:, 0, 4], j_theta[:, 0, 5] = -u * r2, -u * r4, -u * r6
    j_theta[:, 1, 3], j_theta[:, 1, 4], j_theta[:, 1, 5] = -v * r2, -v * r4, -v * r6
    # decentering and thin prism through g1 = s1 + p1, g2 = s2 + p2, g3 = 2 p1, g4 = 2 p2
    uu, uv, vv = u * u, u * v, v * v
    j_theta[:, 0, 6] = -(3 * uu + vv)  # p1
    j_theta[:, 1, 6] = -2 * uv
    j_theta[:, 0, 7] = -2 * uv  # p2
    j_theta[:, 1, 7] = -(uu + 3 * vv)
    j_theta[:, 0, 8] = -(uu + vv)  # s1
    j_theta[:, 1, 9] = -(uu + vv)  # s2
    j_centroid = np.empty((n, 2, 2), dtype=dtype)
    j_centroid[:, 0, 0] = 1 - dx_u
    j_centroid[:, 0, 1] = -dx_v
    j_centroid[:, 1, 0] = -dy_u
    j_centroid[:, 1, 1] = 1 - dy_v
    q = np.stack([u - dx, v - dy], axis=-1)
    return q, j_theta, j_centroid


def unit_vector_jacobians(
    x_px: np.ndarray, y_px: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors and their analytic Jacobians.

    Returns ``(b, J_theta, J_centroid)``: b (N, 3); J_theta (N, 3, 10) = db/d theta (F in pixels);
    J_centroid (N, 3, 2) = db/d(x, y). Uses db/dw = (I - b b^T) / |w| for w = (u', v', F).
    """
    q, jq_theta, jq_centroid = ideal_offset_jacobians(x_px, y_px, theta)
    dtype = q.dtype
    n = q.shape[0]
    w = np.empty((n, 3), dtype=dtype)
    w[:, :2] = q
    w[:, 2] = theta[0]
    # every sum written out in index order (the reference model's float32 order, onboard.linalg32): a port gets
    # the same bits; numpy's sum over an axis and its batched matmul do not state theirs
    norm = np.sqrt(w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1] + w[:, 2] * w[:, 2])
    b = w / norm[:, None]
    proj = (np.eye(3, dtype=dtype)[None] - b[:, :, None] * b[:, None, :]) / norm[:, None, None]
    jw_theta = np.zeros((n, 3, 10), dtype=dtype)
    jw_theta[:, :2, :] = jq_theta
    jw_theta[:, 2, 0] = 1
    # over m = 0, 1, 2 in order (onboard.linalg32.sum_seq's order, written out: a 3-term sum costs 5 passes)
    j_theta = proj[:, :, 0, None] * jw_theta[:, None, 0, :]
    j_theta += proj[:, :, 1, None] * jw_theta[:, None, 1, :]
    j_theta += proj[:, :, 2, None] * jw_theta[:, None, 2, :]
    j_centroid = proj[:, :, 0, None] * jq_centroid[:, None, 0, :] + proj[:, :, 1, None] * jq_centroid[:, None, 1, :]
    return b, j_theta, j_centroid


def offsets_from_direction(b_sensor: np.ndarray, focal_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame direction(s) (N, 3) -> ideal offsets (F b_x / b_z, F b_y / b_z) [px]."""
    return focal_px * b_sensor[:, 0] / b_sensor[:, 2], focal_px * b_sensor[:, 1] / b_sensor[:, 2]


def unit_to_pixels(b_sensor: np.ndarray, theta: np.ndarray, tol_px: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame directions -> measured centroids (x, y) [px]: the inverse of :func:`pixels_to_unit`.

    Solves u - dx(u, v) = F b_x / b_z, v - dy(u, v) = F b_y / b_z by Newton's method on the 2 x 2 system (exact
    Jacobian from :func:`distortion_partials`), starting from the ideal point. Stops when every update is below
    ``tol_px`` or after 8 iterations. Used by simulators only; the sensor never inverts.
    Raises ValueError if a direction is behind the camera or the iteration does not converge.
    """
    if np.any(b_sensor[:, 2] <= 0):
        raise ValueError("direction behind the camera (b_z <= 0)")
    qu, qv = offsets_from_direction(b_sensor, theta[0])
    u, v = qu.copy(), qv.copy()
    step = np.inf
    for _ in range(_INVERSE_MAX_ITER):
        dx, dy = distortion_px(u, v, theta)
        ru, rv = u - dx - qu, v - dy - qv
        dx_u, dx_v, dy_u, dy_v = distortion_partials(u, v, theta)
        a, b, c, d = 1 - dx_u, -dx_v, -dy_u, 1 - dy_v
        det = a * d - b * c
        du = (d * ru - b * rv) / det
        dv = (a * rv - c * ru) / det
        u, v = u - du, v - dv
        step = float(np.max(np.abs(du) + np.abs(dv), initial=0.0))
        if step < tol_px:
            break
    if not step < max(tol_px, 1e-6):
        raise ValueError(f"distortion inverse did not converge (last step {step:.3g} px)")
    return u + theta[1], v + theta[2]


def radec_to_unit(ra_rad: np.ndarray, dec_rad: np.ndarray) -> np.ndarray:
    """Catalogue direction r = (cos dec cos ra, cos dec sin ra, sin dec), shape (N, 3) (docs/camera-model.md)."""
    cd = np.cos(dec_rad)
    return np.stack([cd * np.cos(ra_rad), cd * np.sin(ra_rad), np.sin(dec_rad)], axis=-1)


def unit_to_radec(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`radec_to_unit`: (ra in [0, 2 pi), dec) [rad]."""
    ra = np.mod(np.arctan2(r[:, 1], r[:, 0]), 2 * np.pi)
    dec = np.arctan2(r[:, 2], np.hypot(r[:, 0], r[:, 1]))
    return ra, dec
