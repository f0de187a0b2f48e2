"""The noise map in a crowded field (hostlink.images.background.local_noise_map, through the centroid's extraction).

Known defect, kept as a strict expected failure so that the fix is noticed: each mesh box's noise is
(P97.725 - P50) / 2 of its filtered pixels, and once stars fill more than 2.3 % of a box its upper 2-sigma point lies
on their light. With one star every 30 px (200-30000 ADU, PSF sigma 1 px, noise 5 ADU) the map's median reads
34.5 ADU (SEP's own clipped map: 4.98 ADU), the detection threshold rises with it (171 of 676 stars lost) and every
``sigma_px`` is 6.9 times too large (centroid errors over ``sigma_px``: standard deviation 0.14); one star every
40 px: 7.1 ADU (pull 0.71), every 55 px (granasat's density): 5.7 ADU, every 100 px: 5.15 ADU. (P84.13 - P50),
equally blind to a clipped lower half, reads 5.63, 5.32 and 5.15 ADU at 30, 40 and 55 px.)"""

import numpy as np
import pytest

from hostlink.images.centroid import CentroidOptions
from hostlink.images.centroid.screen import _extract
from hostlink.sky.render import pixel_integrated_gaussian

#: The rendered noise [ADU] and how far the map may read from it: the median of the map over a frame of 800 x 800
#: px is a median of ~150 box estimates, each of ~4000 correlated pixels (a few per cent), and SEP's clipped map,
#: blind to the stars, reads 4.98 here.
NOISE_ADU, TOLERANCE = 5.0, 0.20


def _crowded_frame(spacing_px: int) -> np.ndarray:
    size = 800
    rng = np.random.default_rng(9)
    gx, gy = np.meshgrid(np.arange(20, size - 20, spacing_px), np.arange(20, size - 20, spacing_px))
    x = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    y = gy.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    flux = 10 ** rng.uniform(2.3, 4.5, x.size)
    axis = np.arange(float(size))
    image = np.full((size, size), 100.0)
    for xi, yi, fi in zip(x, y, flux, strict=True):
        r0, c0 = int(yi) - 8, int(xi) - 8
        rows, cols = axis[r0 : r0 + 17], axis[c0 : c0 + 17]
        image[r0 : r0 + 17, c0 : c0 + 17] += fi * np.outer(
            pixel_integrated_gaussian(rows, yi, 1.0), pixel_integrated_gaussian(cols, xi, 1.0)
        )
    return image + rng.normal(0.0, NOISE_ADU, image.shape)


def test_the_noise_map_of_a_sparse_field_is_the_noise():
    _, rms, *_ = _extract(_crowded_frame(100), CentroidOptions())
    assert abs(float(np.median(rms)) / NOISE_ADU - 1.0) < TOLERANCE


@pytest.mark.xfail(strict=True, reason="stars above 2.3 % of a mesh box inflate its upper-percentile noise (docstring)")
def test_the_noise_map_of_a_crowded_field_is_the_noise():
    _, rms, *_ = _extract(_crowded_frame(30), CentroidOptions())
    assert abs(float(np.median(rms)) / NOISE_ADU - 1.0) < TOLERANCE
