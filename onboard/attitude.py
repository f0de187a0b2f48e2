"""Attitude from matched star vectors, and the ship attitude of seed 001, dtype-generic.

- :func:`attitude_from_vectors`: the C with b = C r minimising Wahba's loss sum w_i |b_i - C r_i|^2, by the SVD of
  the attitude profile matrix B = sum w_i b_i r_i^T (Markley 1988): C = U diag(1, 1, det U det V) V^T, for two or
  more non-parallel stars at any attitude (no 180-deg singularity as in QUEST), then two Gauss-Newton steps on the
  same loss, which give back the precision a float32 SVD loses when the field is small (a 10-deg field makes B
  nearly rank one: its singular vectors are then good only to eps / gap, 3x the float32 floor of the inputs).
- :func:`attitude_covariance`: the QUEST measurement-model covariance (Shuster & Oh 1981), the Cramer-Rao bound
  of the attitude error for isotropic direction noise: P = (sum sigma_i^-2 (I - b_i b_i^T))^-1 [rad^2], body axes.
- Ship attitude (seed 001 sec. 3.1, Tables 2, 5, eq. 26): the body frame is x bow, y mast (up), z starboard, the
  local frame north-up-east; a (yaw, pitch, roll) triple means the frame rotation R1(roll) R3(pitch) R2(-yaw)
  (yaw from north toward east about the up axis, then pitch about starboard, then roll about the bow). This is the
  one convention that reproduces eq. 26 from Table 5's angles (to its 4 printed digits), and it serves both the
  mounting (body -> sensor) and the ship (local -> body): R_gs = R_bs R_gb (eq. 5-6).
"""

from __future__ import annotations

import numpy as np

from onboard.earth import rot_x, rot_y, rot_z

#: The second singular value of B, relative to the first, below which the stars are treated as collinear.
_COLLINEAR_RATIO = 1e-6
#: Gauss-Newton steps after the SVD (:func:`_refine`); one reaches the float32 floor, the second confirms it.
_REFINEMENT_STEPS = 2


class DegenerateGeometry(ValueError):
    """Fewer than two non-parallel star directions: the attitude is not determined."""


def rotation_from_profile(profile: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Markley's SVD solution of Wahba's problem from the attitude profile matrix B = sum w b r^T: the rotation
    C = U diag(1, 1, det U det V) V^T maximising sum w b . C r, and the singular values of B. Works on one (3, 3)
    matrix or a stack (..., 3, 3) (the host's batch calibration solves every frame at once), in the input dtype."""
    u, s, vt = np.linalg.svd(profile)
    d = np.linalg.det(u) * np.linalg.det(vt)
    u[..., :, 2] *= d[..., None]
    return u @ vt, s


def attitude_from_vectors(b: np.ndarray, r: np.ndarray, weights=None) -> np.ndarray:
    """Attitude C (3, 3) with b = C r from matched unit vectors b (N, 3, sensor) and r (N, 3, reference), N >= 2.

    ``weights`` (N,): e.g. 1 / sigma_i^2; default equal. SVD solution of Wahba's problem (Markley 1988), in the dtype
    of ``b``. Raises :class:`DegenerateGeometry` for fewer than two usable non-parallel stars.
    """
    dtype = np.result_type(b, r)
    b = np.asarray(b, dtype=dtype)
    r = np.asarray(r, dtype=dtype)
    if b.ndim != 2 or b.shape[1] != 3 or b.shape != r.shape:
        raise ValueError(f"b and r must both be (N, 3), got {b.shape} and {r.shape}")
    w = np.ones(b.shape[0], dtype=dtype) if weights is None else np.asarray(weights, dtype=dtype)
    if b.shape[0] < 2:
        raise DegenerateGeometry(f"{b.shape[0]} star(s): an attitude needs at least 2")
    profile = (b * w[:, None]).T @ r  # B = sum w b r^T
    c, s = rotation_from_profile(profile)
    if not s[1] > s[0] * dtype.type(_COLLINEAR_RATIO):
        raise DegenerateGeometry("the star directions are (nearly) parallel: the attitude is not determined")
    for _ in range(_REFINEMENT_STEPS):
        c = _refine(b, r, w, c)
    return c


def small_rotation(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix R with R p = p + phi x p + ... for a rotation vector phi (3,) [rad] (Rodrigues, exact)."""
    dt = phi.dtype.type
    angle2 = np.sum(phi * phi)
    # sin(a)/a and (1 - cos a)/a^2 by their series: |phi| is a residual correction (< 1e-3 rad), 3 terms are exact
    s = dt(1) - angle2 / dt(6) + angle2 * angle2 / dt(120)
    k = dt(0.5) - angle2 / dt(24) + angle2 * angle2 / dt(720)
    x = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]], dtype=phi.dtype)
    return np.eye(3, dtype=phi.dtype) + s * x + k * (x @ x)


def _refine(b: np.ndarray, r: np.ndarray, w: np.ndarray, c: np.ndarray) -> np.ndarray:
    """One Gauss-Newton step on Wahba's loss about C: with p = C r and b = p + phi x p, the least-squares phi is
    (sum w (I - p p^T))^-1 sum w p x (b - p). The differences b - p are small and exact in float32, so this recovers
    the precision a float32 SVD loses for a small field of view (its singular vectors are only good to eps / gap)."""
    p = r @ c.T
    info = np.einsum("n,nij->ij", w, np.eye(3, dtype=c.dtype)[None] - p[:, :, None] * p[:, None, :])
    g = np.sum(w[:, None] * np.cross(p, b - p), axis=0)
    return small_rotation(np.linalg.solve(info, g)) @ c


def euler_matrix(yaw_rad, pitch_rad, roll_rad, dtype=np.float64) -> np.ndarray:
    """Seed 001's yaw/pitch/roll -> frame rotation R1(roll) R3(pitch) R2(-yaw) (module docstring); e.g. eq. 26's
    R_bs from Table 5, or R_gb (local north-up-east -> ship body) from Table 2."""
    return rot_x(roll_rad, dtype) @ rot_z(pitch_rad, dtype) @ rot_y(-np.asarray(yaw_rad), dtype)


def euler_angles(m: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_matrix`: (yaw, pitch, roll) [rad], yaw in [0, 2 pi), pitch in [-pi/2, pi/2].

    Row 0 of R1(r) R3(p) R2(-y) is (cos p cos y, sin p, cos p sin y); column 1 is (sin p, cos r cos p,
    -sin r cos p).
    """
    m = np.asarray(m)
    pitch = np.arcsin(np.clip(m[0, 1], -1, 1))
    yaw = np.mod(np.arctan2(m[0, 2], m[0, 0]), m.dtype.type(2 * np.pi))
    roll = np.arctan2(-m[2, 1], m[1, 1])
    return yaw, pitch, roll


def ship_attitude(c_local_to_sensor: np.ndarray, mounting_body_to_sensor: np.ndarray) -> tuple[float, float, float]:
    """Ship (yaw, pitch, roll) [rad] from the sensor attitude in the local frame R_gs (b = R_gs r_local) and the
    mounting matrix R_bs: R_gb = R_bs^T R_gs (seed 001 eq. 5-6, 21)."""
    return euler_angles(np.asarray(mounting_body_to_sensor).T @ np.asarray(c_local_to_sensor))


def residuals_rad(b: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Angle [rad] between each b_i and C r_i (N,), by atan2 (accurate for small angles)."""
    p = r @ np.asarray(c, dtype=r.dtype).T
    cross = np.cross(b, p)
    return np.arctan2(np.sqrt(np.sum(cross * cross, axis=1)), np.sum(b * p, axis=1))


def attitude_with_rejection(
    b: np.ndarray, r: np.ndarray, threshold_rad: float, min_stars: int = 3, weights=None
) -> tuple[np.ndarray, np.ndarray]:
    """Attitude (b = C r) after dropping, one at a time, the star with the largest residual while it exceeds
    ``threshold_rad`` and more than ``min_stars`` remain (a misidentified star is off by degrees, a good one by the
    noise). Returns (C, inlier mask (N,)). At most N - min_stars extra solutions: a bounded cost."""
    n = b.shape[0]
    keep = np.ones(n, dtype=bool)
    w = np.ones(n, dtype=b.dtype) if weights is None else np.asarray(weights, dtype=b.dtype)
    c = attitude_from_vectors(b, r, w)
    while int(keep.sum()) > min_stars:
        res = np.where(keep, residuals_rad(b, r, c), b.dtype.type(-1))
        worst = int(np.argmax(res))
        if not res[worst] > threshold_rad:
            break
        keep[worst] = False
        c = attitude_from_vectors(b[keep], r[keep], w[keep])
    return c, keep
