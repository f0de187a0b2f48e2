"""The host's batch Wahba solver (Newton's polar iteration, the SVD where that is not the same rotation) gives the
rotations of the sensor's SVD formula, ``onboard.attitude.rotation_from_profile``, for every kind of profile matrix."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.calibration import frames
from hostlink.calibration.frames import rotations_from_profiles, wahba_attitudes
from onboard.attitude import rotation_from_profile


def _rotations(rng: np.random.Generator, m: int) -> np.ndarray:
    q = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0]
    q[np.linalg.det(q) < 0, :, 0] *= -1.0
    return q


def _profiles(rng: np.random.Generator, m: int, singular_values: tuple[float, float, float]) -> np.ndarray:
    """B = U diag(s) V^T with random rotations U, V."""
    u, v = _rotations(rng, m), _rotations(rng, m)
    return (u * np.asarray(singular_values)[None, None, :]) @ v.transpose(0, 2, 1)


def _bound(singular_values: tuple[float, float, float]) -> float:
    """The rotation is determined to the rounding of B over the sum of its two smallest singular values."""
    return 2e-14 * singular_values[0] / (singular_values[1] + singular_values[2])


@pytest.mark.parametrize(
    "singular_values",
    [(1.0, 0.9, 0.8), (30.0, 0.3, 0.2), (1.0, 1e-3, 7e-4), (1.0, 1e-5, 8e-6)],
    ids=["round", "wide-field", "narrow-field", "very-narrow"],
)
def test_rotations_equal_the_svd_formula_for_fields_of_any_width(singular_values):
    """A frame's profile matrix has one large singular value and two of the field's width squared: Newton's iteration
    solves it (the result is not the SVD's bit for bit) and reaches the SVD's rotation to the problem's rounding,
    orthonormal, a rotation."""
    profile = _profiles(np.random.default_rng(1), 500, singular_values)
    expected = rotation_from_profile(profile)[0]
    got = rotations_from_profiles(profile)
    assert not np.array_equal(got, expected)  # the polar iteration ran
    assert np.max(np.abs(got - expected)) < _bound(singular_values)
    assert np.max(np.abs(np.einsum("mji,mjk->mik", got, got) - np.eye(3))) < 1e-14
    assert np.all(np.linalg.det(got) > 0.0)


def test_newton_converges_in_a_few_scaled_steps(monkeypatch):
    """With Higham's scaling the iteration converges in 5-6 steps even for a narrow field (singular values 1 and
    1e-5): with at most 8 it still solves every frame (unscaled, it would need ~20 and fall back to the SVD)."""
    monkeypatch.setattr(frames, "POLAR_MAX_STEPS", 8)
    singular_values = (1.0, 1e-5, 8e-6)
    profile = _profiles(np.random.default_rng(4), 200, singular_values)
    expected = rotation_from_profile(profile)[0]
    got = rotations_from_profiles(profile)
    assert not np.any(np.all(got == expected, axis=(1, 2)))  # no frame left to the SVD
    assert np.max(np.abs(got - expected)) < _bound(singular_values)


def test_frames_not_converged_go_to_the_svd(monkeypatch):
    """A frame the iteration has not settled within its steps gets the SVD's rotation, bit for bit."""
    monkeypatch.setattr(frames, "POLAR_MAX_STEPS", 1)
    profile = _profiles(np.random.default_rng(5), 50, (1.0, 1e-3, 7e-4))
    np.testing.assert_array_equal(rotations_from_profiles(profile), rotation_from_profile(profile)[0])


def test_profiles_below_the_determinant_threshold_go_to_the_svd():
    """det(B) / |B|_F^3 just below :data:`POLAR_MIN_DET`: the SVD, bit for bit; just above: the iteration."""
    s_small = np.sqrt(frames.POLAR_MIN_DET)  # singular values (1, s, s): det / |B|_F^3 ~ s^2
    below = _profiles(np.random.default_rng(6), 20, (1.0, 0.9 * s_small, 0.9 * s_small))
    above = _profiles(np.random.default_rng(7), 20, (1.0, 1.2 * s_small, 1.2 * s_small))
    np.testing.assert_array_equal(rotations_from_profiles(below), rotation_from_profile(below)[0])
    got, expected = rotations_from_profiles(above), rotation_from_profile(above)[0]
    assert not np.any(np.all(got == expected, axis=(1, 2)))
    assert np.max(np.abs(got - expected)) < _bound((1.0, 1.2 * s_small, 1.2 * s_small))


def test_rank_two_reflected_and_zero_profiles_get_the_svd_rotation():
    """Two stars (rank 2), a profile with det < 0 (Markley's rotation is then not the polar factor) and an empty
    frame: the SVD's rotation bit for bit, whatever the other frames of the stack."""
    rng = np.random.default_rng(2)
    good = _profiles(rng, 4, (1.0, 0.01, 0.008))
    rank_two = _profiles(rng, 1, (1.0, 0.01, 0.0))
    reflected = _profiles(rng, 1, (1.0, 0.01, 0.008))
    reflected[:, :, 0] *= -1.0
    profile = np.concatenate([good[:2], rank_two, reflected, np.zeros((1, 3, 3)), good[2:]])
    expected = rotation_from_profile(profile)[0]
    got = rotations_from_profiles(profile)
    np.testing.assert_array_equal(got[2:5], rotation_from_profile(profile[2:5])[0])
    assert np.max(np.abs(got - expected)) < 1e-12
    assert np.all(np.linalg.det(got) > 0.0)


def test_attitudes_of_frames_recover_the_rotation_of_noise_free_stars():
    """b = C r exactly: every frame's attitude is C, whatever its number of stars (2 to 30) and field."""
    rng = np.random.default_rng(3)
    counts = rng.integers(2, 31, size=200)
    starts = np.concatenate([[0], np.cumsum(counts)])
    truth = _rotations(rng, counts.size)
    r = rng.normal(size=(int(starts[-1]), 3)) * np.array([0.05, 0.05, 1.0])
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    b = np.einsum("nij,nj->ni", np.repeat(truth, counts, axis=0), r)
    got = wahba_attitudes(b, r, starts)
    assert np.max(np.abs(got - truth)) < 1e-12


def test_batched_3x3_inverse_matches_lapack_and_refuses_a_singular_block():
    """The attitude blocks' written-out inverse (transposed cofactors over the determinant) against np.linalg.inv,
    to the blocks' condition number times the rounding; an exactly singular block raises as np.linalg.inv does."""
    rng = np.random.default_rng(8)
    x = rng.normal(size=(300, 3, 3))
    blocks = x @ x.transpose(0, 2, 1) + 1e-2 * np.eye(3)  # symmetric positive definite, as A = J_phi^T W J_phi
    cond = np.linalg.cond(blocks)
    expected = np.linalg.inv(blocks)
    got = frames.inverse_3x3(blocks)
    scale = np.abs(expected).max(axis=(1, 2))
    assert np.all(np.abs(got - expected).max(axis=(1, 2)) <= 1e-15 * cond * scale)
    singular = blocks.copy()
    singular[5] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    with pytest.raises(np.linalg.LinAlgError):
        frames.inverse_3x3(singular)
