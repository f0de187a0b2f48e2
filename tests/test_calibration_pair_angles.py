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
