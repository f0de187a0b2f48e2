"""The one camera model (docs/camera-model.md): Jacobians vs finite differences, the inverse, and float32 vs float64."""

import numpy as np
import pytest

from hostlink.files.params import load_params
from onboard.camera import (
    distortion_px,
    ideal_offset_jacobians,
    offsets_to_unit,
    pixels_to_unit,
    radec_to_unit,
    unit_to_pixels,
    unit_to_radec,
    unit_vector_jacobians,
)
from onboard.params import CameraParams, Distortion

# A camera with every Weng term switched on, each producing a few tenths of a pixel at the corner, as after a
# launch shock: large enough that a wrong sign or a missing factor would show, small enough to stay monotonic.
FULL_WENG = CameraParams(
    focal_length_mm=50.0,
    pixel_pitch_um=5.5,
    principal_point_px=(1030.3, 1018.7),
    image_size_px=(2048, 2048),
    distortion=Distortion(k1=-3.0e-9, k2=2.0e-15, k3=-4.0e-22, p1=1.5e-7, p2=-2.0e-7, s1=8.0e-8, s2=-6.0e-8),
)
#: Seed 004's simulated camera (package data): radial k1, k2 only.
SEED004 = load_params("builtin:seed004_camera")


def _grid(params, n=15):
    w, h = params.image_size_px
    gx, gy = np.meshgrid(np.linspace(-0.5, w - 0.5, n), np.linspace(-0.5, h - 0.5, n))
    return gx.ravel(), gy.ravel()


def _fd_steps(params):
    """Central-difference steps: each perturbs the corner offset by ~1e-3 px, where the truncation error
    (~step^2) and the round-off (~1e-16 / step) are both far below the 1e-6 relative tolerance."""
    rmax = float(np.hypot(*params.image_size_px))
    f_px = params.focal_length_px
    return [f_px * 1e-6, 1e-3, 1e-3, 1e-3 / rmax**3, 1e-3 / rmax**5, 1e-3 / rmax**7] + [1e-3 / rmax**2] * 4


@pytest.mark.parametrize("params", [FULL_WENG, SEED004], ids=["full-weng", "seed004"])
def test_unit_vector_jacobian_matches_central_differences_for_every_parameter(params):
    x, y = _grid(params)
    theta = params.model_vector()
    _, j_theta, _ = unit_vector_jacobians(x, y, theta)
    for k, h in enumerate(_fd_steps(params)):
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd = (pixels_to_unit(x, y, tp) - pixels_to_unit(x, y, tm)) / (2 * h)
        scale = np.max(np.abs(j_theta[:, :, k]))
        assert scale > 0, f"parameter {k} has no effect"
        # central differences are O(h^2) accurate: 1e-6 relative leaves four orders of margin over what we see
        assert np.max(np.abs(fd - j_theta[:, :, k])) <= 1e-6 * scale, f"parameter {k}"


@pytest.mark.parametrize("params", [FULL_WENG, SEED004], ids=["full-weng", "seed004"])
def test_centroid_jacobians_match_central_differences(params):
    x, y = _grid(params)
    theta = params.model_vector()
    _, _, jb_c = unit_vector_jacobians(x, y, theta)
    _, _, jq_c = ideal_offset_jacobians(x, y, theta)
    h = 1e-3  # px: the mapping is a low-order polynomial, so O(h^2) truncation is ~1e-12 relative
    for axis, (dx, dy) in enumerate(((h, 0.0), (0.0, h))):
        fd_b = (pixels_to_unit(x + dx, y + dy, theta) - pixels_to_unit(x - dx, y - dy, theta)) / (2 * h)
        assert np.max(np.abs(fd_b - jb_c[:, :, axis])) <= 1e-7 * np.max(np.abs(jb_c[:, :, axis]))
        qp = np.stack(ideal_offset_jacobians(x + dx, y + dy, theta)[0].T)
        qm = np.stack(ideal_offset_jacobians(x - dx, y - dy, theta)[0].T)
        fd_q = ((qp - qm) / (2 * h)).T
        assert np.max(np.abs(fd_q - jq_c[:, :, axis])) <= 1e-8


def test_ideal_offset_parameter_jacobian_matches_central_differences():
    x, y = _grid(FULL_WENG)
    theta = FULL_WENG.model_vector()
    _, jq, _ = ideal_offset_jacobians(x, y, theta)
    assert np.all(jq[:, :, 0] == 0), "ideal offsets do not depend on the focal length"
    for k, h in enumerate(_fd_steps(FULL_WENG)):
        if k == 0:
            continue
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd = (ideal_offset_jacobians(x, y, tp)[0] - ideal_offset_jacobians(x, y, tm)[0]) / (2 * h)
        assert np.max(np.abs(fd - jq[:, :, k])) <= 1e-6 * np.max(np.abs(jq[:, :, k])), f"parameter {k}"


def test_distortion_follows_weng_formula_term_by_term():
    # seed 000 eq. 7 with g1 = s1 + p1, g2 = s2 + p2, g3 = 2 p1, g4 = 2 p2, written out independently here
    u, v = np.array([300.0, -700.0]), np.array([-450.0, 120.0])
    d = FULL_WENG.distortion
    g1, g2, g3, g4 = d.s1 + d.p1, d.s2 + d.p2, 2 * d.p1, 2 * d.p2
    r2 = u**2 + v**2
    rad = d.k1 * r2 + d.k2 * r2**2 + d.k3 * r2**3
    dx_ref = (g1 + g3) * u**2 + g4 * u * v + g1 * v**2 + u * rad
    dy_ref = g2 * u**2 + g3 * u * v + (g2 + g4) * v**2 + v * rad
    dx, dy = distortion_px(u, v, FULL_WENG.model_vector())
    np.testing.assert_allclose(dx, dx_ref, rtol=1e-13)
    np.testing.assert_allclose(dy, dy_ref, rtol=1e-13)


def test_direction_to_pixel_inverse_round_trips_to_1e_9_px():
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.5, 2047.5, 500)
    y = rng.uniform(-0.5, 2047.5, 500)
    theta = FULL_WENG.model_vector()
    b = pixels_to_unit(x, y, theta)
    x2, y2 = unit_to_pixels(b, theta)
    # Newton converges quadratically; 1e-9 px is ~1e4 float64 ulps of a 2000 px coordinate
    assert np.max(np.abs(x2 - x)) < 1e-9 and np.max(np.abs(y2 - y)) < 1e-9


def test_undistorted_camera_is_a_pinhole_with_sensor_axes_along_column_and_row():
    cam = CameraParams(100.0, 10.0, (500.0, 400.0), (1000, 800))
    b = pixels_to_unit(np.array([500.0, 600.0, 500.0]), np.array([400.0, 400.0, 500.0]), cam.model_vector())
    np.testing.assert_allclose(b[0], [0, 0, 1], atol=1e-15)
    f_px = cam.focal_length_px
    np.testing.assert_allclose(b[1], np.array([100.0, 0, f_px]) / np.hypot(100.0, f_px), rtol=1e-15)
    np.testing.assert_allclose(b[2], np.array([0, 100.0, f_px]) / np.hypot(100.0, f_px), rtol=1e-15)


def test_float32_camera_agrees_with_float64_within_documented_bound():
    """Documented bound: evaluating the model in float32 moves a unit vector by at most 2e-7 rad (0.04 arcsec),
    i.e. about 3.5 float32 unit round-offs (2^-24 = 6e-8) accumulated over the ~10 roundings of the correction and
    the normalisation. At F = 9000 px that is 0.002 px, far below the 0.01 px centroid noise of the best sensors."""
    rng = np.random.default_rng(2)
    for params in (FULL_WENG, SEED004):
        w, h = params.image_size_px
        x32 = rng.uniform(-0.5, w - 0.5, 2000).astype(np.float32)
        y32 = rng.uniform(-0.5, h - 0.5, 2000).astype(np.float32)
        b32 = pixels_to_unit(x32, y32, params.model_vector(np.float32))
        assert b32.dtype == np.float32, "the model must not promote float32 inputs"
        b64 = pixels_to_unit(x32.astype(np.float64), y32.astype(np.float64), params.model_vector())
        angle = np.linalg.norm(np.cross(b32.astype(np.float64), b64), axis=1)
        assert np.max(angle) < 2e-7
        _, j32, jc32 = unit_vector_jacobians(x32, y32, params.model_vector(np.float32))
        assert j32.dtype == np.float32 and jc32.dtype == np.float32


def test_radec_unit_vector_round_trip():
    rng = np.random.default_rng(3)
    ra = rng.uniform(0, 2 * np.pi, 100)
    dec = rng.uniform(-np.pi / 2, np.pi / 2, 100)
    ra2, dec2 = unit_to_radec(radec_to_unit(ra, dec))
    np.testing.assert_allclose(ra2, ra, atol=1e-12)
    np.testing.assert_allclose(dec2, dec, atol=1e-12)
    np.testing.assert_allclose(radec_to_unit(np.array([0.0]), np.array([np.pi / 2]))[0], [0, 0, 1], atol=1e-15)


@pytest.mark.parametrize("params", [FULL_WENG, SEED004], ids=["full-weng", "seed004"])
def test_applied_distortion_partials_jacobian_matches_complex_step(params):
    """d(P w)/d theta in closed form against the complex step of distortion_partials (Squire and Trapp 1998: no
    subtraction, so exact to round-off for this polynomial; 1e-12 relative is ~1e4 unit round-offs of the sums)."""
    from onboard.camera import distortion_partials, distortion_partials_applied_jacobian

    x, y = _grid(params)
    theta = params.model_vector()
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=x.size), rng.normal(size=x.size)
    got = distortion_partials_applied_jacobian(x - theta[1], y - theta[2], theta, a, b)
    h = 1e-30
    for k in range(10):
        step = np.zeros(10, dtype=complex)
        step[k] = 1j * h * max(abs(theta[k]), 1e-30)
        th = theta + step
        dx_u, dx_v, dy_u, dy_v = distortion_partials(x - th[1], y - th[2], th)
        want = np.stack([dx_u * a + dx_v * b, dy_u * a + dy_v * b], axis=1).imag / step[k].imag
        scale = np.max(np.abs(want)) + 1e-300
        np.testing.assert_allclose(got[:, :, k] / scale, want / scale, rtol=0, atol=1e-12, err_msg=f"column {k}")


def test_applied_distortion_partials_jacobian_keeps_float32():
    """The sensor's dtype in, the sensor's dtype out: float32 within 1e-5 relative of float64 (the columns are
    sums of a few terms of mixed sign at the detector's corner: ~100 float32 round-offs of the largest term)."""
    from onboard.camera import distortion_partials_applied_jacobian

    x, y = _grid(FULL_WENG)
    t64 = FULL_WENG.model_vector()
    u, v = x - t64[1], y - t64[2]
    ones = np.ones_like(u)
    j64 = distortion_partials_applied_jacobian(u, v, t64, ones, -ones)
    t32 = FULL_WENG.model_vector(np.float32)
    f32 = np.float32
    j32 = distortion_partials_applied_jacobian(u.astype(f32), v.astype(f32), t32, ones.astype(f32), -ones.astype(f32))
    assert j32.dtype == np.float32
    col_scale = np.maximum(np.max(np.abs(j64), axis=(0, 1)), 1e-300)  # F column: zero
    np.testing.assert_allclose(j32 / col_scale, j64 / col_scale, rtol=0, atol=1e-5)


def test_unit_vectors_take_the_dtype_of_their_offsets():
    """offsets_to_unit computes in the offsets' float type (float32 stays float32: the sensor's), in float64 for
    integer offsets, and in the common type of mixed ones, with the focal length in that type; the result is unit."""
    u = np.array([-700, 0, 3, 512])
    v = np.array([250, 0, -4, -512])
    as64 = offsets_to_unit(u.astype(np.float64), v.astype(np.float64), 5000.0)
    np.testing.assert_allclose(np.linalg.norm(as64, axis=1), 1.0, rtol=0, atol=2e-16)
    got = offsets_to_unit(u, v, 5000)
    assert got.dtype == np.float64 and np.array_equal(got, as64)
    got32 = offsets_to_unit(u.astype(np.float32), v.astype(np.float32), np.float32(5000.0))
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, as64, rtol=0, atol=2e-7)
    mixed = offsets_to_unit(u.astype(np.float32), v.astype(np.float64), 5000.0)
    assert mixed.dtype == np.float64 and np.array_equal(mixed, as64)  # integer-valued offsets: exact in float32
