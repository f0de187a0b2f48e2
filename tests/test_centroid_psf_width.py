"""The PSF model's width fit (hostlink.images.centroid.windows, package docstring step 4): its analytic derivative in
the width agrees with finite differences of the renderer's pixel-integrated Gaussian, and on noiseless stars drawn
with that model it returns the width they were drawn with."""

import numpy as np
import pytest

from hostlink.images.centroid.windows import _psf_width_fit_px
from hostlink.sky.render import pixel_integrated_gaussian, pixel_integrated_gaussian_dwidth


@pytest.mark.parametrize("sigma_px", [0.45, 0.77, 1.3, 2.5])
def test_width_derivative_matches_central_differences(sigma_px):
    centres = np.arange(-8.0, 9.0)
    source = 0.37
    h = 1e-5
    numeric = (
        pixel_integrated_gaussian(centres, source, sigma_px + h)
        - pixel_integrated_gaussian(centres, source, sigma_px - h)
    ) / (2 * h)
    # central differences err by h^2 / 6 x the third derivative (< 1e-9 here) plus ~1e-16 / h of rounding (~1e-11)
    np.testing.assert_allclose(pixel_integrated_gaussian_dwidth(centres, source, sigma_px), numeric, rtol=0, atol=1e-8)


@pytest.mark.parametrize("sigma_px", [0.5, 0.77, 1.2])
def test_noiseless_stars_give_back_their_width(sigma_px):
    rng = np.random.default_rng(7)
    image = np.full((80, 80), 20.0)  # a flat background, fitted as B
    # a 3 x 3 grid 20 px apart, random sub-pixel places and fluxes: a neighbour's light in a star's stamp (+-6 px at
    # most) lies >= 14 px, 11 sigma, from it (< 1e-25 of its flux), so the model is exact and the least-squares width
    # is the drawn one to the fit's convergence (rel 1e-6: 12 Gauss-Newton steps from 25 % wide converge
    # quadratically far below it)
    gx, gy = np.meshgrid([20.0, 40.0, 60.0], [20.0, 40.0, 60.0])
    x, y = gx.ravel() + rng.uniform(-0.5, 0.5, 9), gy.ravel() + rng.uniform(-0.5, 0.5, 9)
    cols = np.arange(80.0)
    for xi, yi, flux in zip(x, y, rng.uniform(500, 5000, 9), strict=True):
        image += flux * np.outer(
            pixel_integrated_gaussian(cols, yi, sigma_px), pixel_integrated_gaussian(cols, xi, sigma_px)
        )
    # started 25 % wide (r50's window is wider than the model for an undersampled star), from the nearest pixels
    fitted = _psf_width_fit_px(image, np.round(x), np.round(y), 1.25 * sigma_px)
    assert fitted == pytest.approx(sigma_px, rel=1e-6)
