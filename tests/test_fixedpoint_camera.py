"""The fixed-point front end (onboard/fixedpoint.py) against the one camera model and interstar code in float64.

Error budget of a Q30 unit vector, from the formats (module docstring of onboard.fixedpoint), in Q30 steps 2^-30:
the final rounding (1/2) and the reciprocal square root (about 2 after three Newton steps); the ideal offsets u', v'
(a handful of rounded terms, each half a Q30 step of S px: a few S/F steps of b); and w's grid (2^-qw normalised,
i.e. max(F, 4S) 2^-30 px over |w| >= F px). Together |b_fixed - b| <= 2^-30 (4 + 8 S / F): 5.4 steps for the seed-004
camera (S = 1024 px, F = 5852 px), i.e. 2.9e-5 px on the detector; measured 1.5 steps (8e-6 px).
"""

import math

import numpy as np
import pytest
from recursive_synth import SEED004_TRUE, make_frames

from onboard import fixedpoint as fx
from onboard.camera import ideal_offsets, pixels_to_unit, unit_vector_jacobians
from onboard.interstar import difference_residuals, independent_pairs, order_for_pairs, pair_covariance
from onboard.params import CameraParams, Distortion

#: seed 004's camera with every Weng term present at a realistic size (0.5-2 px at the detector corner)
FULL = CameraParams(
    70.2262,
    12.0,
    (500.0, 530.0),
    (1024, 1024),
    Distortion(k1=-2.0e-10, k2=3.5e-15, k3=-4e-21, p1=2e-7, p2=-1.5e-7, s1=1e-7, s2=-2e-7),
)
NOISE_PX = 0.05


def unit_bound(cam: fx.FixedCamera) -> float:
    """|b_fixed - b_float64| per component: 2^-30 B of onboard.fixedpoint.error_bounds_q30 (4 + sqrt 2 (D + 2) S / F,
    D ~ 3-4 for small coefficients: about the 4 + 8 S / F this test module first stated)."""
    return 2.0**-30 * fx.error_bounds_q30(cam)[1]


def dense_grid_steps(size_px: int, step_px: float):
    """Every centroid of a grid with ``step_px`` spacing over the whole detector, edges and corners included, in the
    wire's Q10 steps."""
    g = np.rint(np.append(np.arange(-0.5, size_px - 0.5, step_px), size_px - 0.5) * 1024).astype(np.int64)
    x, y = np.meshgrid(g, g)
    return x.ravel(), y.ravel()


@pytest.mark.parametrize("camera", [SEED004_TRUE, FULL], ids=["seed004", "all-terms"])
def test_fixed_unit_vectors_match_the_float64_camera_model_on_a_dense_grid(camera):
    cam = fx.fixed_camera(camera.model_vector(np.float32), camera.image_size_px)
    x, y = dense_grid_steps(1024, 4.0)  # 66 049 centroids
    b = fx.pixels_to_unit_q30(x, y, cam)
    b64 = pixels_to_unit(x * 2.0**-10, y * 2.0**-10, cam.theta_q)
    err = np.abs(b * 2.0**-30 - b64).max()
    assert err <= unit_bound(cam), (err * 2**30, unit_bound(cam) * 2**30)  # derived bound: 5.4 steps of 2^-30
    assert err * cam.theta_q[0] < 3e-5  # the same bound on the detector: under 3e-5 px (measured 8e-6 px)


def test_fixed_ideal_offsets_are_within_a_few_q30_steps_of_the_float64_weng_correction():
    cam = fx.fixed_camera(FULL.model_vector(np.float32), FULL.image_size_px)
    x, y = dense_grid_steps(1024, 8.0)
    u, v = fx.ideal_offsets_q30(x, y, cam)
    u64, v64 = ideal_offsets(x * 2.0**-10, y * 2.0**-10, cam.theta_q)
    step_px = 2.0 ** (cam.s - 30)  # one Q30 normalised step: 9.5e-7 px at S = 1024
    err_px = max(np.abs(u * step_px - u64).max(), np.abs(v * step_px - v64).max())
    assert err_px < 4 * step_px, err_px / step_px  # at most 8 rounded terms of half a step each (measured ~1 step)


def test_float32_parameters_convert_to_the_fixed_formats_exactly():
    # 28-bit coefficient mantissas hold float32's 24 bits; x0, y0, F sit on grids finer than their float32 ulp
    for camera in (SEED004_TRUE, FULL):
        theta32 = camera.model_vector(np.float32)
        cam = fx.fixed_camera(theta32, camera.image_size_px)
        np.testing.assert_array_equal(cam.theta_q, theta32.astype(np.float64))


def test_fixed_residuals_stay_far_below_the_pair_noise():
    """Q61 residuals from Q30 b and r against the float64 residuals of unrounded directions: the front end's error
    over the 2n-3 pairs of 200 frames, as a fraction of each pair's 1-sigma at 0.05 px and in pixels."""
    theta32 = FULL.model_vector(np.float32)
    cam = fx.fixed_camera(theta32, FULL.image_size_px)
    frames = make_frames(FULL, 200, NOISE_PX, seed=5)
    ratios, px = [], []
    for fr in frames:
        xs, ys = np.rint(fr.x_px * 1024).astype(np.int64), np.rint(fr.y_px * 1024).astype(np.int64)
        o = order_for_pairs(xs, ys)
        xs, ys, r = xs[o], ys[o], fr.r[o]
        i, j = independent_pairs(o.size)
        e_fixed = fx.difference_residuals_q61(fx.pixels_to_unit_q30(xs, ys, cam), fx.quantise_unit_q30(r), i, j)
        b, _, jc = unit_vector_jacobians(xs * 2.0**-10, ys * 2.0**-10, cam.theta_q)
        e64 = difference_residuals(b, r, i, j)
        sigma = np.sqrt(np.diag(pair_covariance(b, jc, i, j, NOISE_PX)))
        d = e_fixed * 2.0**-61 - e64
        ratios.append(d / sigma)
        # a centroid shift dx moves e_ij by about |b_i - b_j| dx / F: the error as a displacement on the detector
        px.append(d * cam.theta_q[0] / np.linalg.norm(b[i] - b[j], axis=1))
    ratios, px = np.concatenate(ratios), np.concatenate(px)
    # b within 5.4 steps (2^-30) on each star: |de| <= |b_i - b_j| 2 sqrt(3) 5.4 2^-30, i.e. 1.1e-4 px against
    # the pair's sqrt(2) 0.05 px: 1.6e-3 of its noise at worst (measured RMS ~1e-4)
    assert np.abs(ratios).max() < 2e-3, np.abs(ratios).max()
    assert np.abs(px).max() < 1.2e-4, np.abs(px).max()
    assert np.sqrt(np.mean(ratios**2)) < 5e-4  # RMS: a quarter of the worst case at most (random rounding)


def test_reciprocal_square_root_is_accurate_to_q30_over_its_whole_input_range():
    rng = np.random.default_rng(0)
    n2 = np.concatenate(
        [
            [2**50, 2**50 + 1, 2**60, 3 * 2**60 - 1, 2**61 - 1, 2**61, 2**62 - 1],
            rng.integers(2**50, 3 * 2**60, 5000, dtype=np.int64),
        ]
    ).astype(np.int64)
    y, k = fx.rsqrt_q30(n2)
    for a, yy, kk in zip(n2.tolist(), y.tolist(), k.tolist(), strict=True):
        # exact check in Python integers: y^2 n2 / 2^(60 + 2k) = 1 within 2^-28: y within 2 steps of 2^-30
        # (relative 2^-29: Newton's 1.5e-11, the rounding of a and of the last step), doubled by the square
        # (measured 2.7 2^-30 over 200 000 draws)
        rel = abs(yy * yy * a - (1 << (60 + 2 * kk))) / (1 << (60 + 2 * kk))
        assert rel < 2.0**-28, (a, rel)


def test_integer_bit_length_matches_python():
    rng = np.random.default_rng(1)
    x = np.concatenate([2 ** np.arange(63, dtype=np.int64), rng.integers(1, 2**62, 2000, dtype=np.int64)])
    x = x[x > 0]
    got = fx.bit_length(x)
    assert got.tolist() == [int(v).bit_length() for v in x.tolist()]


def test_catalogue_vectors_quantise_to_half_a_q30_step():
    rng = np.random.default_rng(2)
    r = rng.normal(size=(1000, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    q = fx.quantise_unit_q30(r)
    assert q.dtype == np.int64 and np.abs(q * 2.0**-30 - r).max() <= 2.0**-31  # round to nearest
    assert np.abs(q).max() <= 2**30


def test_the_rsqrt_table_is_built_from_integers_and_starts_within_3_percent():
    i = np.arange(8, 33)
    centre = (i + 0.5) * 2.0**26 / 2.0**31  # alpha at the bin centre
    assert np.allclose(fx.RSQRT_TABLE * 2.0**-30, 1 / np.sqrt(centre), rtol=2.0**-30, atol=0)
    worst = max(abs(math.sqrt((k + 0.5) / k) - 1) for k in range(8, 33))  # bin edge against its centre
    assert worst < 0.031  # the 3.1 % the Newton schedule (3 steps to 1.5e-11) assumes
