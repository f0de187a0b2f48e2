"""Per-frame helpers, vectorised over frames: the least-squares attitude fit and small-rotation updates.

The attitude of every frame at once: the profile matrices B = sum_k w_k b_k r_k^T are accumulated per frame here and
solved for Markley's rotation (Markley 1988; ``onboard.attitude.rotation_from_profile``, the formula the sensor uses),
so b = C r as in docs/camera-model.md: as the polar factor of B by Newton's iteration where that is the same
rotation, by the SVD elsewhere (:func:`rotations_from_profiles`).
"""

from __future__ import annotations

import numpy as np

from hostlink.calibration.data import frame_chunks
from onboard.attitude import rotation_from_profile

#: Newton steps of :func:`rotations_from_profiles` at most. From B / |B|_F the scaled iteration takes 5-6 for the
#: profile matrices of star fields (singular values 1 and ~1e-2..1e-4: the field's width squared).
POLAR_MAX_STEPS = 30
#: Smallest det(B) / |B|_F^3 the polar iteration is used for; below it (two stars, (nearly) collinear ones, a
#: reflection), and where it has not converged, the SVD.
POLAR_MIN_DET = 1e-12
#: A Newton step moving no entry of X by more than this ends the iteration: the convergence is quadratic (the error
#: after a step is about half the square of the step), so what it leaves is ~1e-18, below rounding.
POLAR_STEP_TOL = 1e-9


def wahba_attitudes(
    b: np.ndarray, r: np.ndarray, frame_starts: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares attitude per frame, (M, 3, 3), with b_k ~ C r_k (Markley's rotation of the profile matrix,
    :func:`rotations_from_profiles`).

    b, r: (N, 3) unit vectors grouped by frame; weights (N,) >= 0 (default 1). A frame whose weighted stars do
    not fix a rotation (fewer than two non-parallel) gets the best rotation the SVD offers (not unique).
    """
    m = frame_starts.shape[0] - 1
    big_b = np.zeros((m, 3, 3))
    for f0, f1 in frame_chunks(frame_starts, 50_000):  # bounded working memory: (rows, 3, 3) per chunk
        a, z = int(frame_starts[f0]), int(frame_starts[f1])
        # the nine products b_i r_j of every star as rows (9, rows): summed along contiguous rows, the same sums as
        # over a stack of (rows, 3, 3) outer products at a third of the cost
        outer = np.empty((9, z - a))
        bw = b[a:z] if weights is None else b[a:z] * weights[a:z, None]
        for i in range(3):
            for j in range(3):
                np.multiply(bw[:, i], r[a:z, j], out=outer[3 * i + j])
        local = frame_starts[f0:f1] - a
        nonempty = np.diff(frame_starts[f0 : f1 + 1]) > 0
        if np.any(nonempty):
            big_b[f0:f1][nonempty] = np.add.reduceat(outer, local[nonempty], axis=1).T.reshape(-1, 3, 3)
    return rotations_from_profiles(big_b)


def rotations_from_profiles(profile: np.ndarray) -> np.ndarray:
    """Markley's rotation C = U diag(1, 1, det U det V) V^T for each of a stack of profile matrices B = U S V^T
    (M, 3, 3), float64: :func:`onboard.attitude.rotation_from_profile`'s rotations, faster for many frames
    (docs/calibration.md, "Figures behind the constants").

    Where det B > 0 that rotation is U V^T, the orthogonal polar factor of B, which Newton's iteration
    X <- (g X + X^-T / g) / 2 from X = B / |B|_F finds with Higham's Frobenius-norm scaling g = (|X^-1|_F / |X|_F)^1/2
    (Higham 1986, "Computing the polar decomposition", sec. 3); X^-T is the cofactor matrix (the columns' cross
    products) over det X, so each step is a few array operations over all frames instead of an SVD per frame. The
    frames with det B / |B|_F^3 below :data:`POLAR_MIN_DET` or not converged in :data:`POLAR_MAX_STEPS` go to the SVD.
    The matrices are worked on as rows of 9 entries (row-major), each operation one call over all of them."""
    m = profile.shape[0]
    out = np.empty((m, 9))
    solved = np.zeros(m, dtype=bool)
    flat = profile.reshape(m, 9)
    norm = _frobenius(flat)
    x = flat / np.where(norm > 0.0, norm, 1.0)[:, None]
    cof, det = _cofactors(x)
    todo = np.flatnonzero(det > POLAR_MIN_DET)
    x, cof, det = x[todo], cof[todo], det[todo]
    for _ in range(POLAR_MAX_STEPS):
        if todo.size == 0:
            break
        g = np.sqrt(_frobenius(cof) / det / _frobenius(x))
        x_new = g[:, None] * x
        x_new += cof / (g * det)[:, None]
        x_new *= 0.5
        done = np.max(np.abs(x_new - x), axis=1) <= POLAR_STEP_TOL
        out[todo[done]] = x_new[done]
        solved[todo[done]] = True
        x, todo = x_new[~done], todo[~done]
        cof, det = _cofactors(x)
    out = out.reshape(m, 3, 3)
    rest = np.flatnonzero(~solved)
    if rest.size:
        out[rest] = rotation_from_profile(profile[rest])[0]
    return out


def _frobenius(x: np.ndarray) -> np.ndarray:
    """|X|_F of each of a stack of 3 x 3 matrices as rows of 9 entries (M, 9)."""
    return np.sqrt(np.einsum("ij,ij->i", x, x))


#: Cofactor C_ij = X[i+1, j+1] X[i+2, j+2] - X[i+1, j+2] X[i+2, j+1] (indices mod 3) of a row-major 3 x 3 matrix:
#: the flat positions of the four factors of each of the 9 entries.
_COF_INDEX = np.array(
    [[3 * ((i + a) % 3) + (j + b) % 3 for i in range(3) for j in range(3)] for a, b in ((1, 1), (2, 2), (1, 2), (2, 1))]
)


def _cofactors(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cofactor matrices (det X) X^-T of a stack of 3 x 3 matrices as rows of 9 entries (M, 9) (column k: the
    cross product of X's other two columns) and the determinants (the expansion along the first column)."""
    p, q, r, s = (np.take(x, idx, axis=1) for idx in _COF_INDEX)
    cof = p * q - r * s
    det = x[:, 0] * cof[:, 0] + x[:, 3] * cof[:, 3] + x[:, 6] * cof[:, 6]
    return cof, det


def inverse_3x3(a: np.ndarray) -> np.ndarray:
    """The inverses of a stack of 3 x 3 matrices (M, 3, 3): the transposed cofactors over the determinant, written
    out (np.linalg.inv calls LAPACK once per matrix, which for the few hundred attitude blocks of a sub-chunk costs
    several times the arithmetic). Accurate to the matrices' condition number times the rounding, as LU is for the
    well-conditioned attitude blocks. Raises LinAlgError for an exactly singular matrix, as np.linalg.inv does."""
    cof, det = _cofactors(a.reshape(-1, 9))
    if np.any(det == 0.0):
        raise np.linalg.LinAlgError("Singular matrix")
    return (cof / det[:, None]).reshape(-1, 3, 3).transpose(0, 2, 1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v x], shape (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], z, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], z], axis=-1),
        ],
        axis=-2,
    )


def rotation_from_vector(a: np.ndarray) -> np.ndarray:
    """exp([a x]) by Rodrigues' formula, for rotation vectors a (..., 3) [rad]; shape (..., 3, 3): I + s [a x] +
    c [a x]^2 with [a x]^2 = a a^T - |a|^2 I, its nine entries written out (the same numbers as the matrix products
    to rounding, without their small-matrix overhead, which costs more than the arithmetic for a few hundred)."""
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    angle2 = x * x + y * y + z * z
    angle = np.sqrt(angle2)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    # series limits below 1e-8 rad, where sin(x)/x and (1 - cos x)/x^2 equal 1 and 1/2 to double precision
    s = np.where(small, 1.0, np.sin(safe) / safe)
    c = np.where(small, 0.5, (1.0 - np.cos(safe)) / (safe * safe))
    diagonal = 1.0 - c * angle2
    sx, sy, sz = s * x, s * y, s * z
    cxy, cxz, cyz = c * x * y, c * x * z, c * y * z
    out = np.empty(a.shape[:-1] + (3, 3))
    out[..., 0, 0] = diagonal + c * x * x
    out[..., 0, 1] = cxy - sz
    out[..., 0, 2] = cxz + sy
    out[..., 1, 0] = cxy + sz
    out[..., 1, 1] = diagonal + c * y * y
    out[..., 1, 2] = cyz - sx
    out[..., 2, 0] = cxz - sy
    out[..., 2, 1] = cyz + sx
    out[..., 2, 2] = diagonal + c * z * z
    return out


def apply_attitude_increment(attitude: np.ndarray, dphi: np.ndarray) -> np.ndarray:
    """C <- exp(-[dphi x]) C: the update whose first-order effect on s = C r is ds = [s x] dphi."""
    return rotation_from_vector(-dphi) @ attitude


def per_frame_products(
    terms: np.ndarray, right: np.ndarray, weights: np.ndarray, frame_starts: np.ndarray
) -> np.ndarray:
    """sum_k w_k T_k^T R_k over the stars k of each frame, (M, c, d), for per-star matrices T_k (N, r, c) and
    R_k (N, r, d) (here r = 2 residual rows; T the Jacobian columns and the residual, R the attitude columns).

    Frames are laid out padded with zeros to the largest star count, so the sums are one batched matrix product
    per frame (r x nmax rows) instead of one per star; padding adds exact zeros, so every frame's sum is its own
    whatever the other frames of the call (to the rounding of the product's blocking)."""
    m = frame_starts.shape[0] - 1
    counts = np.diff(frame_starts)
    n, r, c = terms.shape
    d = right.shape[2]
    nmax = int(counts.max(initial=0))
    # row k of frame f goes to slot k - start_f of that frame: flat position f * nmax + k - start_f
    flat = np.arange(n) + np.repeat(np.arange(m) * nmax - frame_starts[:-1], counts)
    padded = np.zeros((m * nmax, r * c))
    padded[flat] = terms.reshape(n, r * c)
    padded_r = np.zeros((m * nmax, r * d))
    padded_r[flat] = (right * weights[:, None, None]).reshape(n, r * d)
    return padded.reshape(m, nmax * r, c).transpose(0, 2, 1) @ padded_r.reshape(m, nmax * r, d)


def triad_attitudes(b: np.ndarray, r: np.ndarray, frame_starts: np.ndarray) -> np.ndarray:
    """A closed-form attitude per frame (M, 3, 3), b ~ C r, by TRIAD (Black 1964; Shuster and Oh 1981, sec. II):
    the primary pair is the frame's mean direction (exact under a rotation), the secondary its star farthest from
    that mean (the longest lever arm for the roll). No SVD: a start for Gauss-Newton, within a few centroid-noise
    angles over the pair's separation of the least-squares attitude."""
    counts = np.diff(frame_starts)
    m = counts.shape[0]
    starts = frame_starts[:-1]
    b1 = np.add.reduceat(b, starts, axis=0)
    r1 = np.add.reduceat(r, starts, axis=0)
    # each star's dot product with its frame's summed direction: the cosine to the mean times the frame's |b1| > 0,
    # so the same order within the frame (the products in place in the repeated sums, added in the same order)
    dot3 = np.repeat(b1, counts, axis=0)
    dot3 *= b
    dot = dot3[:, 0] + dot3[:, 1] + dot3[:, 2]
    nmax = int(counts.max(initial=1))
    padded = np.full(m * nmax, np.inf)
    padded[np.arange(b.shape[0]) + np.repeat(np.arange(m) * nmax - starts, counts)] = dot
    far = starts + np.argmin(padded.reshape(m, nmax), axis=1)  # per frame, the star farthest from the mean
    # the measured and the catalogue frames in one call (the arithmetic of a few hundred rows costs less than the calls)
    both = _triad_matrix(np.concatenate([b1, r1]), np.concatenate([b[far], r[far]]))
    return both[:m] @ both[m:].transpose(0, 2, 1)


def _triad_matrix(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """Columns (v1, v1 x v2, v1 x (v1 x v2)), normalised: the TRIAD frame of a vector pair, (M, 3, 3)."""
    t1 = v1 / vector_norms(v1)[:, None]
    t2 = _cross(t1, v2)
    t2 /= vector_norms(t2)[:, None]
    return np.stack([t1, t2, _cross(t1, t2)], axis=2)


def vector_norms(v: np.ndarray) -> np.ndarray:
    """|v| of a stack of 3-vectors (M, 3): np.linalg.norm(v, axis=1)'s numbers, written out (its reduction over an
    axis of three costs several times the arithmetic)."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for stacks of 3-vectors (M, 3): np.cross's products and differences written out (the same numbers,
    without its axis handling, which costs more than the arithmetic for a few hundred vectors)."""
    out = np.empty(a.shape)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out
