"""The fixed-point front end over the space of cameras a sensor may have (docs/camera-model.md, "Supported cameras"):
detectors from a few pixels to 2^20 px a side, square or strips (2048 x 512), fields from ~160 deg (F = S/8) to
F = 2^20 px (a 0.5 deg field on 8192 px), the principal point anywhere on the detector, and every distortion term up
to the edge of the fixed range. For each drawn camera: the C core (onboard/c/fixedpoint.c) refuses exactly the sets
the Python model refuses, and on the others the int64 code equals the same code on exact Python integers (nothing
wraps), the C core's unit vectors equal Python's bit for bit, and the errors of the ideal offsets and of the unit
vectors against the float64 model stay within the bounds derived from the formats (onboard.fixedpoint.error_bounds_q30).
Before those bounds counted the coefficients' amplification, the stated 2^-30 (4 + 8 S / F) failed here: a strong k3
on a strip (2049 x 520, principal point centred, 5 % distortion) erred by 1.7 times it, on a 1 x 137489 strip by 2.9.
Outside the range, one line names the limit."""

from __future__ import annotations

import math
import os
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_fixedpoint_camera import unit_bound

from onboard import fixedpoint as fx
from onboard.camera import ideal_offsets, pixels_to_unit

pytestmark = pytest.mark.skipif(shutil.which(os.environ.get("CC") or "cc") is None, reason="no C compiler")

#: Drawn cameras per property: each costs a few milliseconds (36 edge centroids, twice in Python, once in C).
EXAMPLES = int(os.environ.get("HOSTLINK_CAMERA_EXAMPLES", "300"))
#: Exponents of the normalised coefficients' powers of S (k1 S^2, k2 S^4, k3 S^6, p S, s S).
POWERS = (2, 4, 6, 1, 1, 1, 1)


@pytest.fixture(scope="module")
def lib():
    from hostlink.portkit import estimator_c

    return estimator_c.load()


def side_px() -> st.SearchStrategy[int]:
    """A detector side: the powers of two and their neighbours (where S changes) or any size, 1 .. 2^20."""
    near_power = st.builds(lambda k, d: max(1, min((1 << k) + d, 1 << 20)), st.integers(0, 20), st.integers(-1, 1))
    return st.one_of(near_power, st.integers(1, 1 << 20), st.sampled_from([256, 512, 2048, 3000, 4096, 8192]))


@st.composite
def cameras(draw) -> tuple[np.ndarray, tuple[int, int]]:
    """(float32 model vector, image size) inside fixed_camera's range, or at its edges."""
    w, h = draw(side_px()), draw(side_px())
    s = fx.detector_shift((w, h))
    scale = float(1 << s)
    lo, hi = math.log2(scale / 8), math.log2(fx.MAX_FOCAL_PX)
    f_px = 2.0 ** draw(st.one_of(st.floats(lo, hi), st.sampled_from([lo, hi])))
    x0 = -0.5 + draw(st.sampled_from([0.0, 1.0, 0.5]) | st.floats(0, 1)) * w
    y0 = -0.5 + draw(st.sampled_from([0.0, 1.0, 0.5]) | st.floats(0, 1)) * h
    # each term's share of the range condition's budget at the drawn camera's farthest corner (normalised radius
    # rho), up to 2 budgets: the radial terms add up exactly, the tangential ones at most (the larger of the two
    # 3 P1 + P2 + S1 sums counts), so about one set in six lands outside
    rho2 = max((cx - x0) ** 2 + (cy - y0) ** 2 for cx in (-0.5, w - 0.5) for cy in (-0.5, h - 0.5)) / scale**2
    shares = draw(st.lists(st.floats(0, 1), min_size=7, max_size=7))
    total = draw(st.floats(0, 2.0)) / max(sum(shares), 1e-9)
    signs = draw(st.lists(st.sampled_from([-1.0, 1.0]), min_size=7, max_size=7))
    reach = [rho2, rho2**2, rho2**3] + [3 * math.sqrt(rho2)] * 4
    dist = [
        sign * share * total / max(r, 1e-300) / scale**p
        for sign, share, r, p in zip(signs, shares, reach, POWERS, strict=True)
    ]
    theta = np.array([f_px, x0, y0, *dist], dtype=np.float32)
    return theta, (w, h)


def edge_centroids_q10(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Corners, edges, centre and first/last pixels of the detector in the wire's Q10 steps (6 x 6 positions)."""
    w, h = size
    ex = np.array([-0.5, 0.0, 1.0, w / 2, w - 1.5, w - 0.5])
    ey = np.array([-0.5, 0.0, 1.0, h / 2, h - 1.5, h - 0.5])
    gx, gy = np.meshgrid(np.clip(ex, -0.5, w - 0.5), np.clip(ey, -0.5, h - 0.5))
    return np.rint(gx.ravel() * 1024).astype(np.int64), np.rint(gy.ravel() * 1024).astype(np.int64)


def python_camera(theta: np.ndarray, size: tuple[int, int]) -> fx.FixedCamera | None:
    try:
        return fx.fixed_camera(theta, size)
    except fx.FixedRangeError:
        return None


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(camera=cameras())
def test_c_and_python_agree_and_nothing_wraps_over_the_camera_space(lib, camera):
    from hostlink.portkit.estimator_c import FixedCamera, ptr, ref

    theta, (w, h) = camera
    cam_py = python_camera(theta, (w, h))
    cam_c = FixedCamera()
    status = lib.fixedpoint_camera(ptr(theta), w, h, ref(cam_c))
    assert (status == 0) == (cam_py is not None), (status, theta.tolist(), (w, h))
    if cam_py is None:
        assert status == 5  # inside every other limit by construction: only the distortion budget can be exceeded
        return
    assert np.array_equal(np.array(cam_c.theta_q), cam_py.theta_q)
    x, y = edge_centroids_q10((w, h))
    b = fx.pixels_to_unit_q30(x, y, cam_py)
    exact = fx.pixels_to_unit_q30(x.astype(object), y.astype(object), cam_py)
    assert np.array_equal(exact.astype(np.int64), b)  # int64 never wrapped
    offsets_bound, _ = fx.error_bounds_q30(cam_py)
    u, v = fx.ideal_offsets_q30(x, y, cam_py)
    u64, v64 = ideal_offsets(x * 2.0**-10, y * 2.0**-10, cam_py.theta_q)
    step_px = 2.0 ** (cam_py.s - 30)  # one Q30 normalised step
    err_steps = max(np.abs(u * step_px - u64).max(), np.abs(v * step_px - v64).max()) / step_px
    assert err_steps <= offsets_bound, (err_steps, offsets_bound)
    b64 = pixels_to_unit(x * 2.0**-10, y * 2.0**-10, cam_py.theta_q)
    err = float(np.abs(b * 2.0**-30 - b64).max())
    assert err <= unit_bound(cam_py), (err * 2**30, unit_bound(cam_py) * 2**30)
    for k in range(x.size):
        b_c = np.zeros(3, np.int64)
        assert lib.fixedpoint_pixels_to_unit_q30(int(x[k]), int(y[k]), ref(cam_c), ptr(b_c)) == 0
        assert b_c.tolist() == b[k].tolist()


@pytest.mark.parametrize("size", [(256, 256), (2048, 512), (8192, 8192), (1 << 20, 1 << 20)])
def test_the_longest_focal_length_is_accepted_and_the_next_float32_refused_in_one_line(lib, size):
    from hostlink.portkit.estimator_c import FixedCamera, ptr, ref

    w, h = size
    at_limit = np.array([fx.MAX_FOCAL_PX, (w - 1) / 2, (h - 1) / 2, 0, 0, 0, 0, 0, 0, 0], dtype=np.float32)
    beyond = at_limit.copy()
    beyond[0] = np.nextafter(np.float32(fx.MAX_FOCAL_PX), np.float32(np.inf))
    cam = fx.fixed_camera(at_limit, size)
    assert cam.qw >= 11  # F / S <= 2^19: every shift of w stays far below 64 bits
    assert lib.fixedpoint_camera(ptr(at_limit), w, h, ref(FixedCamera())) == 0
    with pytest.raises(fx.FixedRangeError, match=r"above 2\^20") as refused:
        fx.fixed_camera(beyond, size)
    assert "\n" not in str(refused.value)
    assert lib.fixedpoint_camera(ptr(beyond), w, h, ref(FixedCamera())) == 7  # FIXEDPOINT_ERR_FOCAL_LONG


def test_an_absurd_focal_length_is_refused_not_shifted_past_64_bits(lib):
    """F = 1e30 px once passed fixed_camera and made the front end shift by 2^(30 - qw) with qw = -57: Python raised
    OverflowError (a traceback), C shifted an int64 by 87 bits (undefined behaviour)."""
    from hostlink.portkit.estimator_c import FixedCamera, ptr, ref

    theta = np.array([1e30, 4095.5, 4095.5, 0, 0, 0, 0, 0, 0, 0], dtype=np.float32)
    with pytest.raises(fx.FixedRangeError, match="Q10 centroids"):
        fx.fixed_camera(theta, (8192, 8192))
    assert lib.fixedpoint_camera(ptr(theta), 8192, 8192, ref(FixedCamera())) == 7
