"""The seed methods' interstar normal equations, vectorised over frames, against a per-frame reference.

The reference below is the straightforward form (one frame at a time: order its stars, take its 2n - 3 pairs,
whiten them by their covariance, add H^T P^-1 H), kept here so the batched production code
(``interstar_methods.interstar_normals``) is pinned to it. Tolerances are round-off: the batched code sums the same
terms in a different order, and its batched solves factorise the same matrices.
"""

import numpy as np
import pytest
from synthetic_sessions import synthetic_session

from hostlink.calibration import interstar_methods
from hostlink.calibration.data import build_data
from hostlink.calibration.interstar_methods import (
    _sine_terms,
    calibrate_interstar,
    frame_pair_orders,
    interstar_normals,
)
from hostlink.calibration.model import parameter_columns, parameter_scales
from hostlink.calibration.seed004 import calibrate_seed004
from onboard.camera import unit_vector_jacobians
from onboard.interstar import (
    difference_jacobian,
    difference_residuals,
    independent_pairs,
    order_for_pairs,
    pair_covariance,
)
from onboard.params import ESTIMATE_NAMES, CameraParams, Distortion

TRUTH = CameraParams(70.2, 12.0, (515.0, 505.0), (1024, 1024), Distortion(k1=-8e-10, k2=1e-15, p1=3e-7, s2=-2e-7))
NOMINAL = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))


def reference_orders(data):
    """Per frame, ``order_for_pairs`` on that frame alone, as global rows (flat, frame by frame)."""
    out = np.arange(data.n_obs, dtype=np.int64)
    for f in range(data.n_frames):
        a, b = int(data.frame_starts[f]), int(data.frame_starts[f + 1])
        if b - a >= 3:
            out[a:b] = a + order_for_pairs(data.x_px[a:b], data.y_px[a:b])
    return out


def reference_normals(data, theta, cols, form, orders, col_scale, frame_mask=None, weight_theta=None):
    """One frame at a time: the whitened normal equations of its 2n - 3 pairs, solved frame by frame (pair
    covariances at ``weight_theta``, default ``theta``)."""
    k = cols.size
    normal, grad, cost, n_pairs = np.zeros((k, k)), np.zeros(k), 0.0, 0
    for f in range(data.n_frames):
        a, z = int(data.frame_starts[f]), int(data.frame_starts[f + 1])
        if z - a < 3 or (frame_mask is not None and not frame_mask[f]):
            continue
        rows = orders[a:z]
        b, jb, jc = unit_vector_jacobians(data.x_px[rows], data.y_px[rows], theta)
        jb = jb[:, :, cols] * col_scale
        r = data.r[rows]
        i, j = independent_pairs(rows.size)
        wt = theta if weight_theta is None else weight_theta
        b_w, jb_w, jc_w = unit_vector_jacobians(data.x_px[rows], data.y_px[rows], wt)
        cov = pair_covariance(b_w, jc_w, i, j, 1.0)
        if form == "cos":
            e, h = difference_residuals(b, r, i, j), difference_jacobian(b, jb, i, j)
        else:
            e, h, _ = _sine_terms(b, r, jb, i, j)
            factor = _sine_terms(b_w, r, jb_w[:, :, cols] * col_scale, i, j)[2]
            cov = cov * factor[:, None] * factor[None, :]
        x = np.linalg.solve(cov, np.column_stack([h, e]))
        normal += h.T @ x[:, :k]
        grad += h.T @ x[:, k]
        cost += float(e @ x[:, k])
        n_pairs += e.size
    return normal, grad, cost, n_pairs


@pytest.fixture(scope="module")
def mixed_session():
    """Frames of 3 to 14 stars (many star-count groups), plus frames of 1 and 2 stars that carry no pair."""
    ss = synthetic_session(TRUTH, 80, stars_per_frame=(3, 14), noise_px=0.1, seed=21)
    few = synthetic_session(TRUTH, 6, stars_per_frame=(1, 2), noise_px=0.1, seed=22).data
    d = ss.data
    key = np.concatenate([d.frame_index(), d.n_frames + few.frame_index()])
    data = build_data(
        np.concatenate([d.x_px, few.x_px]), np.concatenate([d.y_px, few.y_px]), np.concatenate([d.r, few.r]), key
    )
    return data


def test_batched_orders_equal_per_frame_orders(mixed_session):
    # the same comparisons on the same numbers: the orders must be identical, not merely close
    np.testing.assert_array_equal(frame_pair_orders(mixed_session), reference_orders(mixed_session))


@pytest.mark.parametrize("form", ["cos", "sin"])
@pytest.mark.parametrize("estimate", [("f", "x0", "y0"), ESTIMATE_NAMES])
def test_batched_normals_equal_per_frame_reference(mixed_session, form, estimate):
    """Across chunk boundaries (a chunk of ~60 stars) and block boundaries inside a star-count group."""
    data = mixed_session
    cols = parameter_columns(estimate)
    scale = parameter_scales(NOMINAL)[cols]
    theta = NOMINAL.model_vector(np.float64)
    orders = frame_pair_orders(data)
    ref = reference_normals(data, theta, cols, form, orders, scale)
    old_block = interstar_methods.PAIR_BLOCK_ELEMENTS
    for chunk_obs, block in ((50_000, old_block), (60, old_block), (60, 1000)):
        interstar_methods.PAIR_BLOCK_ELEMENTS = block
        try:
            got = interstar_normals(data, theta, cols, form, orders, scale, chunk_obs=chunk_obs)
        finally:
            interstar_methods.PAIR_BLOCK_ELEMENTS = old_block
        assert got[3] == ref[3]
        # sums of ~1000 whitened terms in another order: relative round-off ~1e-13, 1e-9 leaves a wide margin
        # while any missing or doubled frame (~1 % of the sum) would fail
        np.testing.assert_allclose(got[0], ref[0], rtol=1e-9, atol=1e-9 * np.abs(ref[0]).max())
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-9, atol=1e-9 * np.abs(ref[1]).max())
        assert got[2] == pytest.approx(ref[2], rel=1e-9)


def test_frame_mask_drops_exactly_the_masked_frames(mixed_session):
    data = mixed_session
    cols = parameter_columns(("f", "x0", "y0", "k1"))
    scale = parameter_scales(NOMINAL)[cols]
    theta = TRUTH.model_vector(np.float64)
    orders = frame_pair_orders(data)
    mask = np.arange(data.n_frames) % 3 != 1
    got = interstar_normals(data, theta, cols, "cos", orders, scale, frame_mask=mask, chunk_obs=100)
    ref = reference_normals(data, theta, cols, "cos", orders, scale, frame_mask=mask)
    assert got[3] == ref[3] < interstar_normals(data, theta, cols, "cos", orders, scale)[3]
    # round-off only (see above)
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-9, atol=1e-9 * np.abs(ref[0]).max())
    assert got[2] == pytest.approx(ref[2], rel=1e-9)


@pytest.mark.parametrize("method", ["cosine", "improved-sine", "seed004"])
def test_methods_give_the_reference_results(mixed_session, method, monkeypatch):
    """Whole methods (Gauss-Newton, LM, the improved alternation) land on the reference's camera to round-off."""
    data = mixed_session

    def run():
        if method == "seed004":
            return calibrate_seed004(data, NOMINAL)
        form = {"cosine": "cos", "improved-sine": "sin"}[method]
        return calibrate_interstar(data, NOMINAL, form, improved=method.startswith("improved"), rounds=2)

    got = run()
    monkeypatch.setattr(
        interstar_methods,
        "interstar_normals",
        lambda d, t, c, f, o, s, m=None, chunk_obs=0, weight_theta=None: reference_normals(
            d, t, c, f, o, s, m, weight_theta
        ),
    )
    ref = run()
    assert len(got.history) == len(ref.history)
    # the iterations see normals equal to ~1e-13 relative, so the cameras agree far inside 1e-6 of a sigma
    # (the parameters' standard deviations are sqrt(diag N^-1) times the noise)
    sigma = np.sqrt(np.diag(np.linalg.inv(ref.normal))) * ref.sigma_estimated_px
    cols = parameter_columns(ref.estimate)
    np.testing.assert_array_less(np.abs(got.theta - ref.theta)[cols], 1e-6 * sigma)
    np.testing.assert_allclose(got.normal, ref.normal, rtol=1e-9, atol=1e-9 * np.abs(ref.normal).max())
    assert got.sigma_estimated_px == pytest.approx(ref.sigma_estimated_px, rel=1e-9)


def test_batched_pair_covariance_and_orders_match_single_frames_in_float32():
    """The onboard helpers accept a stack of frames with the same star count; each slice equals the single-frame
    call in the sensor's float32 too."""
    ss = synthetic_session(TRUTH, 5, stars_per_frame=(9, 9), seed=23)
    d = ss.data
    theta = TRUTH.model_vector(np.float32)
    x, y = d.x_px.astype(np.float32).reshape(5, 9), d.y_px.astype(np.float32).reshape(5, 9)
    b, _, jc = unit_vector_jacobians(x.ravel(), y.ravel(), theta)
    b, jc = b.reshape(5, 9, 3), jc.reshape(5, 9, 3, 2)
    i, j = independent_pairs(9)
    cov = pair_covariance(b, jc, i, j, np.float32(0.05))
    orders = order_for_pairs(x, y)
    assert cov.dtype == np.float32 and orders.dtype == np.int32
    for f in range(5):
        np.testing.assert_array_equal(orders[f], order_for_pairs(x[f], y[f]))
        single = pair_covariance(b[f], jc[f], i, j, np.float32(0.05))
        # float32 products summed in another order by the batched matmul: a few ulp of the largest entry
        np.testing.assert_allclose(cov[f], single, rtol=0, atol=1e-5 * np.abs(single).max())
