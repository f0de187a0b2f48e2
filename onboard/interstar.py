"""Interstar-angle measurements, shared by the onboard recursive estimator and the host's batch methods.

The invariance of interstar angles (seed 000 eq. 3, seed 004 eq. 1): for stars i, j of one frame,
b_i . b_j = r_i . r_j whatever the attitude. Written in the difference form

    m_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2      (= r_i . r_j - b_i . b_j)

the measurement keeps float32's relative precision for small angles, where the plain cosine b_i . b_j ~ 1 loses it
(the cosine of a 5 deg angle differs from 1 by 4e-3, so float32 keeps only ~1e-5 of the information).

With n stars a frame carries only 2n - 3 independent angles (n directions on the sphere, less 3 for the rotation).
:func:`independent_pairs` picks a fixed set of that size, and :func:`pair_covariance` gives their covariance from
the centroid noise, so estimators whiten exactly those pairs instead of treating all n(n-1)/2 as independent.
"""

from __future__ import annotations

import numpy as np

from onboard.linalg32 import sum_seq


def independent_pairs(n_stars: int) -> tuple[np.ndarray, np.ndarray]:
    """2n - 3 pairs that fix n points on the sphere up to a rotation: (0,1), then (0,k) and (1,k) for k >= 2.

    Every star beyond the first two is tied by two angles to the base pair, so the set is independent and complete
    for rigid-body geometry as long as stars 0 and 1 and star k are not collinear (callers order stars so that
    the base pair is well separated: see :func:`order_for_pairs`). Returns int32 index arrays (i, j).
    """
    if n_stars < 2:
        return np.zeros(0, dtype=np.int32), np.zeros(0, dtype=np.int32)
    ks = np.arange(2, n_stars, dtype=np.int32)
    i = np.concatenate([np.zeros(1, np.int32), np.zeros_like(ks), np.ones_like(ks)])
    j = np.concatenate([np.ones(1, np.int32), ks, ks])
    return i, j


def order_for_pairs(x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """Permutation putting a well-separated base pair first: the star farthest from the mean, then the star
    farthest from that one. Bounded work O(n). Returns int32 indices.

    x_px, y_px: (..., n); leading axes are frames of the same star count, ordered independently (the host's batch
    methods order every frame of a session at once). If every star coincides with the first (no second star
    farther away), the next index is the second of the pair, so the result is always a permutation."""
    n = x_px.shape[-1]
    order = np.broadcast_to(np.arange(n, dtype=np.int32), x_px.shape)
    if n < 3:
        return order.copy()
    # the mean as sum_seq / n (onboard.linalg32's order; numpy's mean sums pairwise)
    mean_x = sum_seq(x_px, axis=-1)[..., None] / n
    mean_y = sum_seq(y_px, axis=-1)[..., None] / n
    d0 = (x_px - mean_x) ** 2 + (y_px - mean_y) ** 2
    a = np.argmax(d0, axis=-1)[..., None]
    d1 = (x_px - np.take_along_axis(x_px, a, axis=-1)) ** 2 + (y_px - np.take_along_axis(y_px, a, axis=-1)) ** 2
    b = np.argmax(d1, axis=-1)[..., None]
    b = np.where(b == a, np.where(a == 0, 1, 0), b)
    rest = order[(order != a) & (order != b)].reshape(x_px.shape[:-1] + (n - 2,))
    return np.concatenate([a.astype(np.int32), b.astype(np.int32), rest], axis=-1)


def difference_residuals(b: np.ndarray, r: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Interstar residuals e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 for the given pairs.

    Read as observation minus prediction: the observation is z_ij = -|r_i - r_j|^2 / 2 (catalogue, exact) and the
    model prediction is h_ij(theta) = -|b_i - b_j|^2 / 2, so e = z - h and a Gauss-Newton step solves
    H dtheta = e with H from :func:`difference_jacobian`. Zero for the true camera without noise.
    """
    db = b[i] - b[j]
    dr = r[i] - r[j]
    db2 = db[:, 0] * db[:, 0] + db[:, 1] * db[:, 1] + db[:, 2] * db[:, 2]  # written out: ((x^2 + y^2) + z^2)
    dr2 = dr[:, 0] * dr[:, 0] + dr[:, 1] * dr[:, 1] + dr[:, 2] * dr[:, 2]
    return (db2 - dr2) / 2


def difference_jacobian(b: np.ndarray, jb: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """dh/dtheta for the prediction h_ij = -|b_i - b_j|^2 / 2: -(b_i - b_j)^T (J_i - J_j), shape (P, K),
    for jb = db/dtheta of shape (N, 3, K)."""
    db = b[i] - b[j]
    dj = jb[i] - jb[j]
    return -(db[:, 0, None] * dj[:, 0] + db[:, 1, None] * dj[:, 1] + db[:, 2, None] * dj[:, 2])  # components in order


def pair_covariance(
    b: np.ndarray, jb_centroid: np.ndarray, i: np.ndarray, j: np.ndarray, sigma_px: float
) -> np.ndarray:
    """Covariance (P, P) of the pair predictions h_ij = -|b_i - b_j|^2 / 2 from isotropic centroid noise sigma_px.

    dh_ij/dc_i = -(b_i - b_j)^T Jc_i and dh_ij/dc_j = +(b_i - b_j)^T Jc_j (Jc = db/d(x, y)); pairs that share a
    star are correlated, which is why only 2n - 3 independent pairs are used and whitened together.
    b (..., n, 3) and jb_centroid (..., n, 3, 2): leading axes are frames of the same star count, giving (..., P, P).
    Each entry sums, in this order, the products over the stars the two pairs share: (i_p, i_q), (i_p, j_q),
    (j_p, i_q), (j_p, j_q), each ``g_0 g_0' + g_1 g_1'``, from zero (the order of :mod:`onboard.linalg32`; a
    pair's own two stars are distinct), then times sigma_px^2 in the inputs' dtype."""
    db = b[..., i, :] - b[..., j, :]
    # dh_p/dc at star i_p and at star j_p (..., P, 2), each a 3-term sum over the components in order
    ji, jj = jb_centroid[..., i, :, :], jb_centroid[..., j, :, :]
    gi = -(db[..., 0, None] * ji[..., 0, :] + db[..., 1, None] * ji[..., 1, :] + db[..., 2, None] * ji[..., 2, :])
    gj = db[..., 0, None] * jj[..., 0, :] + db[..., 1, None] * jj[..., 1, :] + db[..., 2, None] * jj[..., 2, :]
    shape = b.shape[:-2] + (i.shape[0], i.shape[0])
    acc, term, tmp = np.zeros(shape, dtype=b.dtype), np.empty(shape, dtype=b.dtype), np.empty(shape, dtype=b.dtype)
    for ga, sa, gb, sb in ((gi, i, gi, i), (gi, i, gj, j), (gj, j, gi, i), (gj, j, gj, j)):
        np.multiply(ga[..., :, None, 0], gb[..., None, :, 0], out=term)
        np.multiply(ga[..., :, None, 1], gb[..., None, :, 1], out=tmp)
        term += tmp
        np.add(acc, term, out=acc, where=sa[:, None] == sb[None, :])  # only where the two pairs share the star
    acc *= np.asarray(sigma_px * sigma_px).astype(b.dtype)
    return acc
