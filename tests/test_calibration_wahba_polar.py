"""The host's batch Wahba solver (Newton's polar iteration, the SVD where that is not the same rotation) gives the
rotations of the sensor's SVD formula, ``onboard.attitude.rotation_from_profile``, for every kind of profile matrix."""

from __future__ import annotations

import numpy as np
import pytest

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


@pytest.mark.parametrize(
    "singular_values",
    [(1.0, 0.9, 0.8), (30.0, 0.3, 0.2), (1.0, 1e-3, 7e-4), (1.0, 1e-5, 8e-6), (5.0, 2e-6, 1e-6)],
    ids=["round", "wide-field", "narrow-field", "very-narrow", "below-the-polar-threshold"],
)
def test_rotations_equal_the_svd_formula_for_fields_of_any_width(singular_values):
    """A frame's profile matrix has one large singular value and two of the field's width squared; the rotation is
    determined to ~1e-16 over the smallest relative singular value, and both solvers reach that."""
    profile = _profiles(np.random.default_rng(1), 500, singular_values)
    expected = rotation_from_profile(profile)[0]
    got = rotations_from_profiles(profile)
    bound = 2e-14 * singular_values[0] / singular_values[2]
    assert np.max(np.abs(got - expected)) < bound
    assert np.max(np.abs(np.einsum("mji,mjk->mik", got, got) - np.eye(3))) < 1e-14
    assert np.all(np.linalg.det(got) > 0.0)


def test_rank_two_reflected_and_zero_profiles_get_the_svd_rotation():
    """Two stars (rank 2), a profile with det < 0 (Markley's rotation is then not the polar factor) and an empty
    frame: the SVD's rotation, as before, whatever the other frames of the stack."""
    rng = np.random.default_rng(2)
    good = _profiles(rng, 4, (1.0, 0.01, 0.008))
    rank_two = _profiles(rng, 1, (1.0, 0.01, 0.0))
    reflected = _profiles(rng, 1, (1.0, 0.01, 0.008))
    reflected[:, :, 0] *= -1.0
    profile = np.concatenate([good[:2], rank_two, reflected, np.zeros((1, 3, 3)), good[2:]])
    expected = rotation_from_profile(profile)[0]
    got = rotations_from_profiles(profile)
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
