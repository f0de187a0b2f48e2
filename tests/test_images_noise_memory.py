"""Large frames (docs/realsky.md "Large frames"): the local noise map's star-light clipping
(background._clipped_box_noise) holds no frame-sized float copy of the image beyond the filtered image itself. Its
peak is counted by tracemalloc (which numpy reports its arrays to), not timed; and the strips it forms the star light
in give the numbers of the whole-frame formula."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy import ndimage

from hostlink.images import background
from hostlink.images.background import (
    _STAR_ISOPHOTE_SIGMAS,
    _STAR_PEAK_SIGMAS,
    _box_constant,
    _star_light,
    _StarLightBuffers,
    filtered_noise_correction,
)

#: What filtered_noise_correction returns, per pixel: the filtered image, the offset and the noise maps (float64)
#: and the pixels where nothing is detected (bool): the floor of its peak [bytes].
_RETURNED_BYTES_PER_PX = 3 * 8 + 1
#: Above that floor at its peak: the grids of boxes (3 % of a pixel each on this frame's 16-px fine boxes), the
#: strips of rows the star light is formed in (1 / 10 of the frame here) [bytes per pixel]. The clipping's own state
#: at its peak is below the floor: the filtered image (8), its pixels in boxes sorted (float32, 4), the mask, the
#: passes' labels (int32, 4) and four bool images (23 bytes). Before, it also held the image over its offset
#: (float64), a second float32 copy in boxes and the labels as intp: 45.8 bytes a pixel on this frame.
_OVERHEAD_BYTES_PER_PX = 3


def _starry_frame(shape: tuple[int, int], n_stars: int, seed: int) -> np.ndarray:
    """Rounded Gaussian noise (sigma 4 ADU) with ``n_stars`` Gaussian stars (sigma 1.5 px, 20-400 ADU peaks)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    image = np.round(rng.normal(size=shape) * 4.0)
    yy, xx = np.mgrid[:h, :w]
    for y, x, peak in zip(
        rng.uniform(0, h, n_stars), rng.uniform(0, w, n_stars), rng.uniform(20, 400, n_stars), strict=True
    ):
        box = (slice(max(0, int(y) - 6), int(y) + 7), slice(max(0, int(x) - 6), int(x) + 7))
        image[box] += peak * np.exp(-((yy[box] - y) ** 2 + (xx[box] - x) ** 2) / (2 * 1.5**2))
    return image


def test_the_noise_correction_peaks_at_little_more_than_what_it_returns(monkeypatch):
    """600 x 800 px (the last row of boxes cut by the border), 400 stars: the clipping makes 4 passes."""
    monkeypatch.setattr(background, "_TAKE_STRIP_ELEMENTS", 64 * 800)  # a strip of 64 rows, as on a large frame
    shape = (600, 800)
    sub, blank, sep_rms = _starry_frame(shape, 400, seed=3), np.zeros(shape, dtype=bool), np.ones(shape)
    passes = []
    monkeypatch.setattr(background, "_star_light", lambda *a: passes.append(1) or _star_light(*a))
    filtered_noise_correction(sub[:100, :100].copy(), np.ones((100, 100)), np.ones((3, 3)), 64, blank[:100, :100])
    passes.clear()  # the first call imported scipy's modules, not counted below
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start = tracemalloc.get_traced_memory()[0]
        out = filtered_noise_correction(sub, sep_rms, np.ones((3, 3)), 64, blank)
        peak = tracemalloc.get_traced_memory()[1] - start
    finally:
        tracemalloc.stop()
    assert len(passes) >= 2  # the clipping's passes ran
    assert sum(a.nbytes for a in out) == _RETURNED_BYTES_PER_PX * sub.size
    assert peak < (_RETURNED_BYTES_PER_PX + _OVERHEAD_BYTES_PER_PX) * sub.size, peak / sub.size


@pytest.mark.parametrize(
    ("shape", "offset_px", "noise_px"),
    [((256, 320), 16, 64), ((250, 300), 16, 64), ((97, 131), 8, 30)],  # whole boxes; cut; boxes not nested
)
def test_the_star_light_in_strips_is_the_whole_frame_formula(shape, offset_px, noise_px):
    """background._star_light forms the image over its offset and the comparisons a strip of rows at a time: the
    same pixels as the whole-frame formula (the image less its box offsets, compared with each box's thresholds,
    8-connected regions above the isophote holding a peak), bit for bit."""
    rng = np.random.default_rng(shape[0])
    image = _starry_frame(shape, 60, seed=shape[1])
    h, w = shape
    ny, nx = -(-h // noise_px), -(-w // noise_px)
    offset = rng.normal(size=(-(-h // offset_px), -(-w // offset_px)))
    noise = rng.uniform(3.0, 5.0, size=(ny, nx))
    padded = (ny * noise_px, nx * noise_px)
    mask = np.ones(padded, dtype=bool)
    mask[:h, :w] = False
    mask[: h // 4, : w // 3] = True  # a blank region

    above = image - _box_constant(offset, offset_px, shape)
    sigma = _box_constant(noise, noise_px, shape)
    isophote = (above > _STAR_ISOPHOTE_SIGMAS * sigma) & ~mask[:h, :w]
    labels, n = ndimage.label(isophote, structure=np.ones((3, 3), dtype=int))
    star = np.zeros(n + 1, dtype=bool)
    star[labels[above > _STAR_PEAK_SIGMAS * sigma]] = True
    star[0] = False
    expected = star[labels]

    buffers = _StarLightBuffers(
        np.zeros(padded, dtype=bool),
        np.zeros(padded, dtype=bool),
        np.empty(padded, dtype=np.int32),
        np.empty(padded, dtype=bool),
    )
    for _ in range(2):  # the buffers reused by a second pass
        light = _star_light(image, offset, offset_px, mask, noise, noise_px, buffers)
        np.testing.assert_array_equal(light[:h, :w], expected)
        assert not light[h:].any() and not light[:, w:].any()
    assert expected.any() and not expected.all()
