"""The report's interstar sums (seed 000 sec. 4.2, Delta_rms) against a plain per-frame, per-pair computation with
arccos, for frames of mixed star counts and any block size; and the count-ordered frame blocks they run in."""

import numpy as np
import pytest

from hostlink.calibration.data import build_data, frame_blocks
from hostlink.calibration.report import interstar_sums_at
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, Distortion

CAMERA = CameraParams(25.0, 5.5, (1030.0, 1020.0), (2048, 2048), Distortion(k1=-3e-9, p1=2e-7))


def _session(seed: int = 3):
    """Frames of 1-9 stars (pixels and slightly rotated true directions), in time order."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 10, size=40)
    key = np.repeat(np.arange(counts.size), counts)
    x_px = rng.uniform(50.0, 2000.0, key.size)
    y_px = rng.uniform(50.0, 2000.0, key.size)
    b = pixels_to_unit(x_px, y_px, CAMERA.model_vector(np.float64))
    r = b + rng.normal(0.0, 2e-5, b.shape)  # catalogue directions a few arcsec off the measured ones
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return build_data(x_px, y_px, r, key), counts


def _reference(data, theta):
    """Sum over every pair i < j of every frame of (angle_b - angle_r)^2 by arccos, and the pair count."""
    b = pixels_to_unit(data.x_px, data.y_px, theta)
    total, count = 0.0, 0
    for f in range(data.n_frames):
        a, z = data.frame_starts[f], data.frame_starts[f + 1]
        for i in range(a, z):
            for j in range(i + 1, z):
                ang_b = np.arccos(np.clip(b[i] @ b[j], -1.0, 1.0))
                ang_r = np.arccos(np.clip(data.r[i] @ data.r[j], -1.0, 1.0))
                total += (ang_b - ang_r) ** 2
                count += 1
    return total, count


@pytest.mark.parametrize("chunk_obs", [1, 7, 50, 10_000])
def test_interstar_sums_equal_the_pairwise_arccos_sums_for_any_block_size(chunk_obs):
    data, counts = _session()
    theta0 = CAMERA.model_vector(np.float64)
    theta1 = theta0.copy()
    theta1[0] *= 1.002  # a focal length 0.2 % long: interstar errors of ~0.2 % of each angle
    got = interstar_sums_at(data, [theta0, theta1], chunk_obs)
    for (total, count), theta in zip(got, [theta0, theta1], strict=True):
        want_total, want_count = _reference(data, theta)
        assert count == want_count == int(np.sum(counts * (counts - 1) // 2))
        # the pairs here are > 14 mrad apart, where arccos is good to ~1e-14 rad: the sums agree to ~1e-9 relative
        assert total == pytest.approx(want_total, rel=1e-9)


def test_frame_blocks_hold_every_frame_once_by_star_count_within_the_row_bound():
    data, counts = _session(seed=5)
    counts[7] = 0  # an empty frame is still placed (it has no rows)
    starts = np.concatenate([[0], np.cumsum(counts)])
    blocks = frame_blocks(starts, 12)
    order = np.concatenate(blocks)
    assert np.array_equal(np.sort(order), np.arange(counts.size))
    assert np.all(np.diff(counts[order]) >= 0)  # ascending star counts
    for block in blocks:
        assert block.size == 1 or counts[block].sum() <= 12
