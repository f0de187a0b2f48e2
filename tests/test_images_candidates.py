"""Issue 30, centroid's faint candidates (hostlink.images.centroid, step 7): they leave the detected stars exactly as
they were, their windowed centroid is Source Extractor's (``sep.winpos``, the outside authority), and their ``snr`` is
a standard normal variable on noise alone."""

import numpy as np
import pytest

from hostlink.images.centroid import CentroidOptions, _snr, _window_iterated, centroid_pixels
from hostlink.sky.render import RenderConfig, render_stars

CONFIG = RenderConfig(hot_pixels=0, psf_sigma_px=1.0)


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(20, 490, 200), rng.uniform(20, 490, 200)
    rendered = render_stars(x, y, rng.uniform(500, 5000, x.size), (512, 512), CONFIG, seed=2)
    return x, y, rendered.image_adu


def test_the_candidates_leave_the_detected_stars_as_they_were(frame):
    _, _, image = frame
    without = centroid_pixels(image, CentroidOptions(candidate_sigma=None), saturation_adu=CONFIG.saturation_adu)
    with_them = centroid_pixels(image, CentroidOptions(), saturation_adu=CONFIG.saturation_adu)
    assert without.candidates is None and with_them.candidates is not None
    for name in ("x_px", "y_px", "flux_adu", "mag", "sigma_px", "saturated"):
        assert np.array_equal(getattr(without, name), getattr(with_them, name))
    assert with_them.report.candidates == with_them.candidates.x_px.size
    assert np.all(with_them.candidates.snr >= CentroidOptions().candidate_sigma)


def test_the_batched_window_is_source_extractors_windowed_centroid(frame):
    """Started at each star's nearest pixel, the batched iteration lands where ``sep.winpos`` does: within 1e-3 px for
    the isolated stars (no other within 10 px: a neighbour's light makes both wander, differently), measured median
    4e-5 px (SEP stops when a step is below 2e-4 px; ours takes 8 steps)."""
    import sep

    x, y, image = frame
    sub = image.astype(np.float64) - np.median(image)
    d = np.hypot(x[:, None] - x[None], y[:, None] - y[None])
    np.fill_diagonal(d, np.inf)
    isolated = d.min(axis=1) > 10.0
    x0, y0 = np.rint(x[isolated]), np.rint(y[isolated])
    ours = np.column_stack(_window_iterated(sub, x0, y0, CONFIG.psf_sigma_px))
    xs, ys, flag = sep.winpos(sub, x0, y0, np.full(x0.size, CONFIG.psf_sigma_px))
    assert isolated.sum() >= 100 and np.all(flag == 0)
    assert np.all(np.hypot(ours[:, 0] - xs, ours[:, 1] - ys) < 1e-3)


def test_the_snr_of_noise_alone_is_standard_normal():
    """White Gaussian noise of 3 ADU, the PSF-fit flux at 5000 random places over its noise: mean 0 and standard
    deviation 1.05 (measured), within 0.05 and 1.0-1.1: the local background (the median of a ring of ~200 pixels)
    adds its own noise, (sum P / sum P^2)^2 x 1.57 sigma^2 / 208 = 10 % of the flux's variance sigma^2 / sum P^2, a 5 %
    larger deviation; the sampling error of 5000 draws is 1 %."""
    rng = np.random.default_rng(4)
    noise = rng.normal(0.0, 3.0, (1000, 1000))
    snr = _snr(noise, np.full_like(noise, 3.0), rng.uniform(20, 980, 5000), rng.uniform(20, 980, 5000), 1.0)
    assert abs(float(np.mean(snr))) < 0.05
    assert 1.0 <= float(np.std(snr)) <= 1.1
