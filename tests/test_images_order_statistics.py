"""The order statistics the centroiding computes by sorting rows instead of numpy's strided partition (for speed,
docs/realsky.md "Time") are numpy's own numbers, bit for bit: the background boxes' percentiles, the stamps' ring
medians and the median of the input frames (ties as 8-bit and JPEG pixels have them, odd and even counts)."""

import numpy as np
import pytest

from hostlink.images.background import _box_blocks, _box_percentiles, _boxes, _masked_box_percentiles
from hostlink.images.centroid.session import _median_frame
from hostlink.images.order_statistics import row_medians, row_percentiles


@pytest.mark.parametrize("n", [1, 7, 64, 100, 256, 4096])
def test_box_percentiles_are_numpys(n):
    rng = np.random.default_rng(n)
    rows = np.round(rng.normal(size=(300, n)) * 6).astype(np.float32)  # ties, as on quantised pixels
    for percents in [(50.0,), (50.0, 97.725), (0.0, 99.9, 100.0)]:
        expected = np.percentile(rows, percents, axis=1).T.astype(np.float64)
        np.testing.assert_array_equal(row_percentiles(rows, percents), expected)


@pytest.mark.parametrize("n", [7, 256, 4096])
def test_box_percentiles_of_rows_with_masked_pixels_are_numpys_of_the_rest(n):
    rng = np.random.default_rng(n)
    rows = np.round(rng.normal(size=(300, n)) * 6).astype(np.float32)
    masked = rng.uniform(size=rows.shape) < rng.uniform(0.0, 0.8, (300, 1))  # a mask, a box cut by the border
    masked[:, -1] = False  # every row keeps a value (_box_percentiles asks no percentile of none)
    rows[masked] = np.nan
    rows[0] = np.nan
    rows[0, 3] = 2.0  # one value left
    counts = np.isfinite(rows).sum(axis=1)
    for percents in [(50.0,), (50.0, 97.725), (0.0, 99.9, 100.0)]:
        out = row_percentiles(rows, percents, counts)
        for k in range(rows.shape[0]):
            expected = np.percentile(rows[k][np.isfinite(rows[k])], percents).astype(np.float64)
            np.testing.assert_array_equal(out[k], expected)


def test_ring_medians_are_numpys_and_a_partial_ring_counts_its_pixels_alone():
    rng = np.random.default_rng(5)
    for p in (119, 120):
        values = np.round(rng.normal(size=(200, p)) * 4)
        valid = np.ones(values.shape, dtype=bool)
        valid[:20, : p // 3] = False  # stamps the border cuts
        valid[20] = False  # no pixel at all
        out = row_medians(values, valid)
        np.testing.assert_array_equal(out[21:], np.median(values[21:], axis=1))
        for k in range(20):
            assert out[k] == np.median(values[k][valid[k]])
        assert np.isnan(out[20])


@pytest.mark.parametrize("frames", [3, 4, 10])
def test_median_frame_is_numpys(frames):
    rng = np.random.default_rng(frames)
    stack = np.round(rng.normal(size=(frames, 40, 50)) * 5).astype(np.float32)
    np.testing.assert_array_equal(_median_frame(stack), np.median(stack, axis=0).astype(np.float64))
    stack[1, 3, 4] = np.nan
    np.testing.assert_array_equal(_median_frame(stack), np.median(stack, axis=0).astype(np.float64))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32, np.float32, np.float64])
def test_median_frame_of_any_pixel_type_is_numpys_without_wrapping(dtype):
    """The mean of the middle two frames is taken as np.median takes it, in float64 for integers (their sum in their
    own type wraps: two uint16 frames of 60000 gave 27232): each integer type's extremes keep their exact median."""
    if np.issubdtype(dtype, np.integer):
        top, bottom = np.iinfo(dtype).max, np.iinfo(dtype).min
        stack = np.array([[[top, bottom]], [[top, bottom]], [[top, bottom]], [[bottom, top]]], dtype=dtype)
        np.testing.assert_array_equal(_median_frame(stack), [[float(top), float(bottom)]])
        np.testing.assert_array_equal(_median_frame(stack), np.median(stack, axis=0).astype(np.float64))
    rng = np.random.default_rng(3)
    stack = rng.integers(0, 256, size=(6, 30, 40)).astype(dtype)
    np.testing.assert_array_equal(_median_frame(stack), np.median(stack, axis=0).astype(np.float64))


def test_median_of_two_uint16_frames_of_60000_is_60000():
    assert _median_frame(np.full((2, 1, 1), 60000, dtype=np.uint16))[0, 0] == 60000.0


@pytest.mark.parametrize("shape", [(256, 320), (250, 300)])  # whole boxes, and boxes the border cuts
def test_each_pass_of_the_clipped_noise_takes_the_box_percentiles_of_the_pixels_left(shape):
    """The boxes laid out once and the stars' light excluded per pass (background._masked_box_percentiles) give
    _box_percentiles' numbers of the image with that light masked, bit for bit, NaN where too few pixels are left."""
    rng = np.random.default_rng(shape[1])
    image = np.round(rng.normal(size=shape) * 6)
    mask = np.zeros(shape, dtype=bool)
    mask[:40, :70] = True  # a blank region: boxes wholly or partly masked
    box = 32
    boxes = _boxes(image, box)
    ny, nx = boxes.grid_shape
    gradient = np.linspace(0.0, 1.0, shape[1])  # from every pixel left to none
    for fraction in (0.0, 0.05, 0.5, gradient):
        stars = rng.uniform(size=shape) < fraction
        excluded = np.ones(boxes.padded_shape, dtype=bool)
        excluded[: shape[0], : shape[1]] = mask | stars
        out = _masked_box_percentiles(boxes, excluded, (50.0, 97.725))
        expected, rows, cols = _box_percentiles(image, mask | stars, box, (50.0, 97.725))
        np.testing.assert_array_equal(out, expected)
        np.testing.assert_array_equal(boxes.row_centres, rows)
        np.testing.assert_array_equal(boxes.col_centres, cols)
        assert out.shape == (ny, nx, 2)
    assert np.isnan(out).any() and np.isfinite(out).any()  # the gradient leaves some boxes too few pixels


def test_a_pass_that_changes_a_few_boxes_sorts_only_those_and_keeps_numpys_numbers():
    """The later passes of the clipped noise change the stars' light in a few boxes: background._masked_box_percentiles
    sorts only the boxes whose pixels left changed since the pass before (its boxes' work rows) and keeps the others;
    every pass still gives _box_percentiles' numbers bit for bit (a star's light grown in one box, in two, then the
    pass before repeated, then a box wholly excluded and one left whole again)."""
    rng = np.random.default_rng(7)
    shape, box = (250, 300), 32  # boxes the border cuts
    image = np.round(rng.normal(size=shape) * 6)
    mask = np.zeros(shape, dtype=bool)
    mask[:40, :70] = True
    boxes = _boxes(image, box)
    stars = rng.uniform(size=shape) < 0.03
    passes = [stars.copy()]
    stars[100:110, 100:112] = True  # one box's star grows
    passes.append(stars.copy())
    stars[200:230, 5:20] = True  # and a star in another
    passes.append(stars.copy())
    passes.append(stars.copy())  # nothing changed
    stars[64:96, 160:192] = True  # a box with every pixel excluded (too few left: NaN)
    stars[:32, 256:] = False  # a border box whole again
    passes.append(stars.copy())
    for light in passes:
        excluded = np.ones(boxes.padded_shape, dtype=bool)
        excluded[: shape[0], : shape[1]] = mask | light
        out = _masked_box_percentiles(boxes, excluded, (50.0, 97.725))
        expected, _, _ = _box_percentiles(image, mask | light, box, (50.0, 97.725))
        np.testing.assert_array_equal(out, expected)
        ny, nx = boxes.grid_shape
        gone = excluded.reshape(ny, box, nx, box).transpose(0, 2, 1, 3).reshape(ny * nx, -1)
        np.testing.assert_array_equal(boxes.work_gone, gone)  # the state kept is this pass's exclusion
        counted = (~gone).sum(axis=1)
        values, _, _, _ = _box_blocks(image, np.zeros(shape, dtype=bool), box)  # the frame as float32 boxes
        kept = np.sort(np.where(gone, np.nan, values), axis=1)
        np.testing.assert_array_equal(boxes.work, kept)  # and each box's pixels left, sorted (NaN last)
        np.testing.assert_array_equal(boxes.work_counted, counted)
