"""Overflow and range of the fixed-point front end at its extremes: the corner pixels of a 4096 x 4096 detector, the
principal point at a corner (the largest radius) or at the centre, the widest field it takes (F = S/8) to a long
focal length, and the largest distortion onboard.params.validate_params accepts (monotonicity) or the fixed range
allows. No overflow: the int64 code equals the same code run on exact Python integers (numpy object arrays), which
any wrap-around would break. Accuracy: within the derived bound of tests/test_fixedpoint_camera.py."""

from functools import cache

import numpy as np
import pytest
from test_fixedpoint_camera import unit_bound

from onboard import fixedpoint as fx
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, Distortion, ParameterError, validate_params

SIDE = 4096
PITCH_UM = 12.0
CORNER_PP = (-0.5, -0.5)
CENTRE_PP = (SIDE / 2 - 0.5, SIDE / 2 - 0.5)
POWERS = {"k1": 2, "k2": 4, "k3": 6, "p1": 1, "p2": 1, "s1": 1, "s2": 1}


def camera(pp, focal_px, **distortion) -> CameraParams:
    return CameraParams(focal_px * PITCH_UM / 1000, PITCH_UM, pp, (SIDE, SIDE), Distortion(**distortion))


@cache
def monotonic_limit(pp, key: str) -> float:
    """Largest positive value of one distortion coefficient that validate_params accepts (bisection to 1e-15
    relative; monotonicity does not depend on F)."""
    lo, hi = 0.0, 10.0 / (2 * SIDE) ** POWERS[key]
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        try:
            validate_params(camera(pp, 4000.0, **{key: mid}))
            lo = mid
        except ParameterError:
            hi = mid
    return lo


def extreme_centroids() -> tuple[np.ndarray, np.ndarray]:
    """Corners, edges and centre of the detector in Q10 steps (every combination of 7 positions per axis)."""
    e = np.array([-0.5, 0.0, 1.0, SIDE / 2, SIDE - 1.5, SIDE - 1.0, SIDE - 0.5])
    gx, gy = np.meshgrid(e, e)
    return np.rint(gx.ravel() * 1024).astype(np.int64), np.rint(gy.ravel() * 1024).astype(np.int64)


def check_exact_and_accurate(params: CameraParams) -> None:
    cam = fx.fixed_camera(params.model_vector(np.float32), params.image_size_px)
    x, y = extreme_centroids()
    b = fx.pixels_to_unit_q30(x, y, cam)
    exact = fx.pixels_to_unit_q30(x.astype(object), y.astype(object), cam)
    assert np.array_equal(exact.astype(np.int64), b)  # int64 never wrapped
    assert np.abs(exact).max() <= 2**30 + 1  # Q30 unit vectors (rounding may add one step)
    b64 = pixels_to_unit(x * 2.0**-10, y * 2.0**-10, cam.theta_q)
    err = np.abs(b * 2.0**-30 - b64).max()
    assert err <= unit_bound(cam), (err * 2**30, unit_bound(cam) * 2**30)  # the derived bound (worst measured 19
    # steps against 67 at F = S/8, where w's grid is coarsest relative to |w|)


@pytest.mark.parametrize("pp", [CORNER_PP, CENTRE_PP], ids=["pp-corner", "pp-centre"])
@pytest.mark.parametrize("focal_px", [512.0, 4000.0, 30000.0], ids=["F=S/8", "F=4000", "F=30000"])
@pytest.mark.parametrize("key", sorted(POWERS))
@pytest.mark.parametrize("sign", [1.0, -1.0], ids=["+", "-"])
def test_largest_distortion_validate_params_accepts_runs_exactly_at_the_detector_corners(pp, focal_px, key, sign):
    value = sign * monotonic_limit(pp, key)
    params = camera(pp, focal_px, **{key: value})
    validate_params(params)  # the set is one a sensor may be given (negative radial terms are always monotonic)
    check_exact_and_accurate(params)


@pytest.mark.parametrize("pp", [CORNER_PP, CENTRE_PP], ids=["pp-corner", "pp-centre"])
def test_every_term_together_at_the_edge_of_the_fixed_range_runs_exactly(pp):
    # the range condition's sum at 0.999, shared over all seven terms with signs that add up at the far corner
    rho2 = max((cx - pp[0]) ** 2 + (cy - pp[1]) ** 2 for cx in (-0.5, SIDE - 0.5) for cy in (-0.5, SIDE - 0.5))
    rho2 /= float(SIDE) ** 2
    share = 0.999 / 6  # k1, k2, k3 and the tangential sum (3|p1| + |p2| + |s1|) weighted by 3
    k = {"k1": -share / rho2 / SIDE**2, "k2": -share / rho2**2 / SIDE**4, "k3": -share / rho2**3 / SIDE**6}
    t = 3 * share / np.sqrt(rho2) / SIDE / 5  # 3|p1| + |p2| + |s1| = 5 t
    params = camera(pp, 4000.0, **k, p1=t, p2=t, s1=t, s2=t)
    validate_params(params)
    check_exact_and_accurate(params)


def test_distortion_beyond_the_fixed_range_is_refused_though_validate_params_accepts_it():
    rho2 = 2.0  # principal point at a corner, far corner at sqrt(2) S
    inside = camera(CORNER_PP, 4000.0, k1=-0.99 / rho2 / SIDE**2)
    outside = camera(CORNER_PP, 4000.0, k1=-1.02 / rho2 / SIDE**2)
    validate_params(outside)  # monotonic: u' = u (1 + |k1| r^2)
    check_exact_and_accurate(inside)
    with pytest.raises(fx.FixedRangeError, match="% of the radius"):
        fx.fixed_camera(outside.model_vector(np.float32), outside.image_size_px)


@pytest.mark.parametrize(
    "theta_change, size, message",
    [
        ({1: 5000.0}, (4096, 4096), "principal point"),
        ({0: 511.0}, (4096, 4096), "below S/8"),
        ({}, (2**20 + 1, 16), "detector side"),
        ({3: float("nan")}, (4096, 4096), "finite"),
    ],
)
def test_parameters_outside_the_formats_are_refused(theta_change, size, message):
    theta = camera(CENTRE_PP, 4000.0).model_vector()
    for k, v in theta_change.items():
        theta[k] = v
    with pytest.raises(fx.FixedRangeError, match=message):
        fx.fixed_camera(theta, size)


def test_a_centroid_off_the_detector_is_refused_and_masked():
    cam = fx.fixed_camera(camera(CORNER_PP, 4000.0).model_vector(), (SIDE, SIDE))
    x = np.array([-512, SIDE * 1024 - 512, -513, SIDE * 1024 - 511], dtype=np.int64)  # edges, then just outside
    y = np.zeros(4, dtype=np.int64)
    assert fx.on_detector(x, y, (SIDE, SIDE)).tolist() == [True, True, False, False]
    assert fx.on_detector(y, x, (SIDE, SIDE)).tolist() == [True, True, False, False]
    fx.pixels_to_unit_q30(x[:2], y[:2], cam)
    with pytest.raises(fx.FixedRangeError, match="off the detector"):
        fx.pixels_to_unit_q30(np.array([SIDE * 1024 * 2], dtype=np.int64), y[:1], cam)


def test_residuals_of_opposite_directions_fit_int64():
    # the largest |b_i - b_j| (antipodal, e.g. against a misidentified reference), with the one step of rounding a
    # Q30 unit vector may carry: |d|^2 = 4 (1 + 2^-30)^2 in Q60, just above 2^62, and e = +-(that) in Q61
    top = 2**30 + 1
    up = np.array([[0, 0, top], [0, 0, -top]], dtype=np.int64)
    same = np.array([[0, 0, top], [0, 0, top]], dtype=np.int64)
    i, j = np.array([0]), np.array([1])
    for b, r, sign in ((up, same, 1), (same, up, -1)):
        e = fx.difference_residuals_q61(b, r, i, j)
        exact = fx.difference_residuals_q61(b.astype(object), r.astype(object), i, j)
        assert int(e[0]) == int(exact[0]) == sign * (2 * top) ** 2  # no wrap-around at the largest value
