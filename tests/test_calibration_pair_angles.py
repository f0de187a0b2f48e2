"""The angle between two unit vectors from their dot product (the voting, the pre-pass and the interstar report all
take their angles from Gram matrices through it): accurate against the cross-product form at every angle, half
angles that double to the angle exactly, and dot products that rounding put outside [-1, 1] clipped."""

import numpy as np

from hostlink.calibration.data import angle_from_dot_rad, half_angle_from_dot_rad


def _unit_pairs(angles_rad: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random unit vectors a and b = a turned by each angle about a random axis perpendicular to a."""
    a = rng.normal(size=(angles_rad.size, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    axis = np.cross(a, rng.normal(size=a.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    c, s = np.cos(angles_rad)[:, None], np.sin(angles_rad)[:, None]
    return a, c * a + s * np.cross(axis, a)


def test_angles_from_dot_products_match_the_cross_product_form_at_every_angle():
    """atan2(|a x b|, a.b) is accurate at any angle; from the dot product alone the chord form is good to the
    rounding of a.b over sin(angle): the dot product of two vectors whose lengths are 1 to ~3e-16 is off by up to
    ~6e-16 (5.1e-16 seen), so 1e-15 / sin(angle): 1e-12 rad at 1 mrad, where arccos would be off by ~1e-8."""
    rng = np.random.default_rng(11)
    angles = np.geomspace(1e-3, 3.1, 2000)
    a, b = _unit_pairs(angles, rng)
    exact = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))
    got = angle_from_dot_rad(np.sum(a * b, axis=1))
    assert np.all(np.abs(got - exact) <= 1e-15 / np.sin(exact))


def test_half_angles_double_to_the_angles_bit_for_bit():
    dots = np.random.default_rng(12).uniform(-1.0, 1.0, 10_000)
    np.testing.assert_array_equal(2.0 * half_angle_from_dot_rad(dots), angle_from_dot_rad(dots))


def test_dot_products_rounded_past_one_give_zero_and_pi():
    """A star's dot product with itself or with a star on the far side can round just beyond +-1: the angle is then
    0 or pi, never NaN."""
    dots = np.array([1.0 + 4e-16, 1.0, -1.0, -1.0 - 4e-16])
    np.testing.assert_array_equal(angle_from_dot_rad(dots), [0.0, 0.0, np.pi, np.pi])
    assert half_angle_from_dot_rad(np.float64(1.0 + 4e-16)) == 0.0


def test_vote_counts_every_frames_disagreeing_pairs_as_one_frame_at_a_time_does():
    """The vote over blocks of one star count (frames of 1 to 14 stars, a fifth of the stars given another star's
    catalogue direction) against the plain per-frame form with the cross-product angle: a star is consistent when
    its angle to at least half of the other stars of its frame agrees within 3 % + 1 mrad; a star alone in its
    frame is not. The field is the largest catalogue angle within a frame, to 1e-12 rad (the chord form's rounding,
    ~1e-15 / sin(angle): test above). Small blocks (chunk_obs) split the frames of one count over several
    blocks."""
    from synthetic_sessions import synthetic_session

    from hostlink.calibration.data import build_data
    from hostlink.calibration.robust import VOTE_ABS_TOL_RAD, VOTE_REL_TOL, consistent_stars_and_field
    from onboard.camera import pixels_to_unit
    from onboard.params import CameraParams

    camera = CameraParams(25.0, 5.5, (1023.5, 1023.5), (2048, 2048))
    many = synthetic_session(camera, 60, stars_per_frame=(3, 14), noise_px=0.1, seed=31).data
    few = synthetic_session(camera, 8, stars_per_frame=(1, 2), noise_px=0.1, seed=32).data
    key = np.concatenate([many.frame_index(), many.n_frames + few.frame_index()])
    r = np.concatenate([many.r, few.r])
    rng = np.random.default_rng(33)
    wrong = rng.choice(r.shape[0], r.shape[0] // 5, replace=False)
    r[wrong] = r[rng.permutation(wrong)]
    data = build_data(np.concatenate([many.x_px, few.x_px]), np.concatenate([many.y_px, few.y_px]), r, key)
    b = pixels_to_unit(data.x_px, data.y_px, camera.model_vector())

    def angles(v):
        cross = np.linalg.norm(np.cross(v[:, None, :], v[None, :, :]), axis=2)
        return np.arctan2(cross, v @ v.T)

    want = np.zeros(data.n_obs, dtype=bool)
    field = 0.0
    for f in range(data.n_frames):
        a, z = int(data.frame_starts[f]), int(data.frame_starts[f + 1])
        ang_r, ang_b = angles(data.r[a:z]), angles(b[a:z])
        agree = np.abs(ang_b - ang_r) <= VOTE_REL_TOL * ang_r + VOTE_ABS_TOL_RAD
        others = z - a - 1
        if others:
            want[a:z] = (agree.sum(axis=1) - 1) / others >= 0.5  # less the star itself
        field = max(field, float(ang_r.max()))
    assert 0 < np.count_nonzero(~want) < data.n_obs
    for chunk_obs in (20_000, 40):
        keep, field_rad = consistent_stars_and_field(data, b, chunk_obs=chunk_obs)
        np.testing.assert_array_equal(keep, want)
        assert abs(field_rad - field) <= 1e-12


def test_gram_matrices_run_on_one_blas_thread_and_restore_the_limit():
    """The per-frame Gram matrices are computed with BLAS on one thread (``one_blas_thread``: OpenBLAS's threads
    cost more than these thin products), the process's limit restored after; the entries are the vectors' dot
    products (to a few ulps: BLAS may fuse the three multiply-adds)."""
    from threadpoolctl import threadpool_info

    from hostlink.calibration.data import gram_matrices, one_blas_thread

    def blas_threads() -> list[int]:
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    before = blas_threads()
    with one_blas_thread():
        assert blas_threads() and all(n == 1 for n in blas_threads())
    assert blas_threads() == before
    v = np.random.default_rng(4).normal(size=(3, 40, 3))
    v /= np.linalg.norm(v, axis=2, keepdims=True)  # unit vectors: |a.b| <= 1, three products summed: ~3 ulps
    g = gram_matrices(v)
    assert blas_threads() == before
    np.testing.assert_allclose(g, np.einsum("mik,mjk->mij", v, v), rtol=0, atol=4 * np.finfo(float).eps)
