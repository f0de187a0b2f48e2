"""The default calibration: a bundle adjustment over the camera and the attitude of every frame.

Measurement model, per identified star k of frame f (CAMERA_MODEL.md):

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

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.data import CalibrationData, frame_chunks, measured_directions
from hostlink.calibration.frames import apply_attitude_increment, wahba_svd
from hostlink.calibration.robust import huber_cost, huber_weights, robust_sigma_2d, vote_consistent_stars
from onboard.camera import distortion_partials, ideal_offset_jacobians, ideal_offsets
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Most stars processed at once in a pass over the data: bounds the working arrays (~1.5 kB per star, ~30 MB per pass).
DEFAULT_CHUNK_OBS = 20_000


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
    step_tol: float = 1e-4  # when a step moves the camera by less than this many standard deviations
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


def _projection(r: np.ndarray, attitude_obs: np.ndarray, focal_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s = C r per star, its ideal-plane projection p = F s_xy / s_z [px], and 1 / s_z."""
    s = np.einsum("nij,nj->ni", attitude_obs, r)
    inv_z = 1.0 / s[:, 2]
    return s, focal_px * s[:, :2] * inv_z[:, None], inv_z


def _inverse_2x2(jc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Entries (i00, i01, i10, i11) of Jc^-1 for a stack of 2 x 2 matrices, written out (numpy's batched
    small-matrix routines cost more in call overhead than the arithmetic)."""
    det = jc[:, 0, 0] * jc[:, 1, 1] - jc[:, 0, 1] * jc[:, 1, 0]
    return jc[:, 1, 1] / det, -jc[:, 0, 1] / det, -jc[:, 1, 0] / det, jc[:, 0, 0] / det


def observation_terms(
    x_px: np.ndarray, y_px: np.ndarray, r: np.ndarray, attitude_obs: np.ndarray, theta: np.ndarray, cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals and their Jacobians for a block of stars.

    attitude_obs: (n, 3, 3) attitude of each star's frame. Returns e (n, 2) [measured px], J_theta (n, 2, K)
    with respect to the model-vector entries ``cols``, J_phi (n, 2, 3) with respect to the frame's rotation
    increment. J_theta is the exact derivative of e, including that of the whitening Jc^-1 (which depends on the
    principal point and the distortion): with the whitening held fixed, the Gauss-Newton fixed point is not the
    minimum of sum |e|^2 and, along the weak principal-point/decentering/attitude direction, lies many standard
    deviations from it (:func:`whitening_jacobian`).
    """
    q, jq_theta, jc = ideal_offset_jacobians(x_px, y_px, theta)
    focal_px = theta[0]
    s, p, inv_z = _projection(r, attitude_obs, focal_px)
    i00, i01, i10, i11 = _inverse_2x2(jc)
    d = q - p
    e = np.stack([i00 * d[:, 0] + i01 * d[:, 1], i10 * d[:, 0] + i11 * d[:, 1]], axis=1)
    jt = jq_theta[:, :, cols]
    f_col = np.flatnonzero(cols == 0)
    if f_col.size:
        jt[:, :, f_col[0]] -= p / focal_px  # dp/dF = p / F; q does not depend on F
    j_theta = np.stack(
        [i00[:, None] * jt[:, 0] + i01[:, None] * jt[:, 1], i10[:, None] * jt[:, 0] + i11[:, None] * jt[:, 1]], axis=1
    )
    j_theta += whitening_jacobian(x_px - theta[1], y_px - theta[2], theta, cols, e, (i00, i01, i10, i11))
    # dp/dphi for s -> s + phi x s: row k of dp/ds times [s]x, i.e. (dp_k/ds) x s, with
    # dp_0/ds = (F/z, 0, -p_0/z) and dp_1/ds = (0, F/z, -p_1/z)
    fz = focal_px * inv_z
    a0z, a1z = -p[:, 0] * inv_z, -p[:, 1] * inv_z
    sx, sy, sz = s[:, 0], s[:, 1], s[:, 2]
    c0 = np.stack([-a0z * sy, a0z * sx - fz * sz, fz * sy], axis=1)
    c1 = np.stack([fz * sz - a1z * sy, a1z * sx, -fz * sx], axis=1)
    j_phi = -np.stack([i00[:, None] * c0 + i01[:, None] * c1, i10[:, None] * c0 + i11[:, None] * c1], axis=1)
    return e, j_theta, j_phi


def whitening_jacobian(
    u: np.ndarray, v: np.ndarray, theta: np.ndarray, cols: np.ndarray, e: np.ndarray, jc_inv: tuple
) -> np.ndarray:
    """d(Jc^-1) / d theta applied to d = Jc e: the part of de/dtheta that comes from the whitening (n, 2, K).

    Jc = I - P with P the distortion partials (``onboard.camera.distortion_partials``), so
    d(Jc^-1)/dtheta_k d = Jc^-1 (dP/dtheta_k) e. P is linear in the coefficients k1..s2, so dP/dtheta_k is P at
    the unit coefficient vector; for the principal point, dP/dx0 = -dP/du and dP/dy0 = -dP/dv, taken by the
    complex step (Squire and Trapp 1998: Im P(u + i h) / h, exact to round-off for this polynomial). F: zero.
    """
    i00, i01, i10, i11 = jc_inv
    out = np.zeros((u.shape[0], 2, cols.size))
    h = 1e-30
    for c, k in enumerate(cols):
        if k == 0:
            continue
        if k in (1, 2):
            du, dv = (-1j * h, 0.0) if k == 1 else (0.0, -1j * h)
            dp = [part.imag / h for part in distortion_partials(u + du, v + dv, theta)]
        else:
            unit = np.zeros(10)
            unit[k] = 1.0
            dp = distortion_partials(u, v, unit)
        p_e0 = dp[0] * e[:, 0] + dp[1] * e[:, 1]  # (dP/dtheta_k) e
        p_e1 = dp[2] * e[:, 0] + dp[3] * e[:, 1]
        out[:, 0, c] = i00 * p_e0 + i01 * p_e1
        out[:, 1, c] = i10 * p_e0 + i11 * p_e1
    return out


def observation_residuals(
    x_px: np.ndarray, y_px: np.ndarray, r: np.ndarray, attitude_obs: np.ndarray, theta: np.ndarray
) -> np.ndarray:
    """The residuals e of :func:`observation_terms` alone (no Jacobians): the cost of a trial step."""
    q_u, q_v = ideal_offsets(x_px, y_px, theta)
    dx_u, dx_v, dy_u, dy_v = distortion_partials(x_px - theta[1], y_px - theta[2], theta)
    _, p, _ = _projection(r, attitude_obs, theta[0])
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
) -> NormalBlocks:
    """Weighted normal-equation blocks, one chunk of frames at a time (memory bounded by ``chunk_obs``).

    Camera columns are multiplied by ``col_scale`` (the step is solved in scaled units)."""
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
        jt = jt * col_scale[None, None, :]
        w = weights[a:b, None, None]
        jt_w = jt * w
        jp_w = jp * w
        flat_w = jt_w.reshape(-1, k)
        blocks.u += flat_w.T @ jt.reshape(-1, k)
        blocks.g += flat_w.T @ e.ravel()
        local = starts[f0:f1] - a
        jp_w_t = jp_w.transpose(0, 2, 1)
        blocks.a[f0:f1] = np.add.reduceat(jp_w_t @ jp, local, axis=0)
        blocks.b[f0:f1] = np.add.reduceat(jt_w.transpose(0, 2, 1) @ jp, local, axis=0)
        blocks.g_phi[f0:f1] = np.add.reduceat((jp_w_t @ e[:, :, None])[:, :, 0], local, axis=0)
        blocks.e[a:b] = e
    return blocks


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
    a_inv = np.linalg.inv(a)
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
    """Per-frame SVD attitude from the measured directions of the given camera (Markley's method)."""
    return wahba_svd(measured_directions(data, theta), data.r, data.frame_starts)


def bundle_adjust(data: CalibrationData, nominal: CameraParams, options: BundleOptions | None = None) -> BundleResult:
    """Calibrate the camera and every frame's attitude by robust Levenberg-Marquardt (see module docstring).

    ``nominal`` gives the starting values and the fixed values of parameters not in ``options.estimate``.
    Raises ValueError if fewer than one frame with three consistent stars remains.
    """
    opt = options or BundleOptions()
    cols = parameter_columns(opt.estimate)
    if cols.size == 0:
        raise ValueError("no parameter to estimate")
    scale = parameter_scales(nominal)[cols]
    theta = nominal.model_vector(np.float64)
    n_input = data.n_obs
    rows_used = np.ones(n_input, dtype=bool)
    n_voted = 0
    if opt.screen:
        consistent = vote_consistent_stars(data, measured_directions(data, theta))
        n_voted = int(np.sum(~consistent))
        fit, kept_rows, _ = data.select(consistent)
        rows_used = kept_rows
    else:
        fit, kept_rows, _ = data.select(np.ones(n_input, dtype=bool))
        rows_used = kept_rows
    input_index = np.flatnonzero(rows_used)  # fit row -> input row
    rows_gated = np.zeros(n_input, dtype=bool)
    if fit.n_frames == 0:
        raise ValueError("no frame with at least 3 consistent identified stars")
    att = initial_attitudes(fit, theta)
    history: list[dict] = []
    n_gated = 0
    damping = 1e-6
    converged = False
    iteration = 0
    e = residuals(fit, theta, att, opt.chunk_obs)
    for _round in range(opt.max_gate_rounds + 1):
        converged = False
        while iteration < opt.max_iter:
            iteration += 1
            norm = np.linalg.norm(e, axis=1)
            sig = robust_sigma_2d(norm)
            w = huber_weights(norm, sig, opt.huber_k)
            cost = huber_cost(norm, sig, opt.huber_k)
            blocks = accumulate_normals(fit, theta, att, cols, w, scale, opt.chunk_obs)
            accepted = False
            for _trial in range(12):
                s, rhs, a_inv = reduced_normal(blocks, damping)
                dx = solve_scaled(s, rhs)
                dphi = np.einsum("mij,mj->mi", a_inv, -blocks.g_phi - np.einsum("mkj,k->mj", blocks.b, dx))
                theta_new = theta.copy()
                theta_new[cols] += dx * scale
                att_new = apply_attitude_increment(att, dphi)
                e_new = residuals(fit, theta_new, att_new, opt.chunk_obs)
                cost_new = huber_cost(np.linalg.norm(e_new, axis=1), sig, opt.huber_k)
                if np.isfinite(cost_new) and cost_new <= cost:
                    accepted = True
                    break
                damping = max(10.0 * damping, 1e-6)
            if not accepted:
                converged = True  # no descent direction left at any damping: at the minimum to round-off
                break
            decrease = (cost - cost_new) / max(cost, 1e-300)
            theta, att, e = theta_new, att_new, e_new
            # the weakest directions (principal point against attitude) need damping far below 1e-6 of the
            # diagonal to move at all: let it fall to zero (a plain Gauss-Newton step) once steps succeed
            damping = damping / 10.0 if damping > 1e-12 else 0.0
            step_sigmas = float(np.sqrt(max(dx @ rhs, 0.0))) / max(sig, 1e-300)
            entry = {
                "iteration": iteration,
                "cost": cost_new,
                "rms_px": float(np.sqrt(np.mean(np.sum(e * e, axis=1)))),
                "robust_sigma_px": sig,
                "damping": damping,
                "step_sigmas": step_sigmas,
                "n_obs": fit.n_obs,
            }
            history.append(entry)
            if opt.progress:
                opt.progress(entry)
            if decrease < opt.ftol or step_sigmas < opt.step_tol:
                converged = True
                break
        norm = np.linalg.norm(e, axis=1)
        sig = robust_sigma_2d(norm)
        bad = norm > opt.gate * sig
        if not np.any(bad) or _round == opt.max_gate_rounds:
            break
        n_gated += int(bad.sum())
        rows_gated[input_index[bad]] = True
        fit_new, kept, frame_kept = fit.select(~bad)
        input_index = input_index[kept]
        att = att[frame_kept]
        fit = fit_new
        if fit.n_frames == 0:
            raise ValueError("every frame lost its stars to outlier gating")
        e = residuals(fit, theta, att, opt.chunk_obs)
        damping = 1e-6
    rows_used = np.zeros(n_input, dtype=bool)
    rows_used[input_index] = True
    m_in = data.select(np.ones(n_input, dtype=bool))[0].n_frames
    # final normal matrix at the solution, plain least squares (unit weights), model-vector units
    ones = np.ones(fit.n_obs)
    blocks = accumulate_normals(fit, theta, att, cols, ones, np.ones(cols.size), opt.chunk_obs)
    s = reduced_normal(blocks, 0.0)[0]
    dof = max(2 * fit.n_obs - cols.size - 3 * fit.n_frames, 1)
    sigma_est = float(np.sqrt(np.sum(blocks.e * blocks.e) / dof))
    sigma = float(opt.noise_px) if opt.noise_px else sigma_est
    cov = covariance_from_normal(s, sigma)
    return BundleResult(
        theta=theta,
        attitudes=att,
        data=fit,
        rows_used=rows_used,
        rows_gated=rows_gated,
        n_rejected_voting=n_voted,
        n_rejected_gating=n_gated,
        n_frames_dropped=int(m_in - fit.n_frames),
        sigma_px=sigma,
        sigma_estimated_px=sigma_est,
        estimate=tuple(ESTIMATE_NAMES[c] for c in cols),
        normal=s,
        normal_u_diag=np.diag(blocks.u).copy(),
        covariance=cov,
        history=history,
        converged=converged,
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
