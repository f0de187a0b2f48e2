"""Centroiding rendered images (hostlink.images.centroid on hostlink.sky.render): accuracy against the Cramer-Rao
bound of the pixel-integrated Gaussian PSF, and the rejection of hot pixels, saturated stars and blended pairs.

Rendered regime (RenderConfig defaults): PSF sigma 1.2 px, sky + dark 40 e-/px, read noise 8 e-, gain 2 e-/ADU.
Stars of 1500, 4000 and 30000 e- have a peak pixel of about 150, 400 and 3000 e- over a per-pixel noise of about
10 e-: peak SNR 15, 40 and 250, from the faint stars a star tracker's identification lives on (background and read
noise dominate) to bright ones whose own shot noise dominates."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hostlink.images.centroid import SATURATED_SIGMA_PX, CentroidOptions, centroid_crb_px, centroid_pixels
from hostlink.sky.render import RenderConfig, render_stars

IMAGE_SIZE = (512, 512)


def _grid_stars(rng: np.random.Generator, n_side: int = 8, spacing_px: float = 60.0):
    """Stars on a grid (isolated: 60 px apart) at random sub-pixel positions."""
    gx, gy = np.meshgrid(np.arange(n_side), np.arange(n_side))
    n = n_side * n_side
    x = 30.0 + spacing_px * gx.ravel() + rng.uniform(-0.5, 0.5, n)
    y = 30.0 + spacing_px * gy.ravel() + rng.uniform(-0.5, 0.5, n)
    return x, y


def _match(det_x, det_y, x, y, radius_px: float = 1.5):
    """Index of the nearest truth star of each detection, and whether it is within ``radius_px``."""
    d = np.hypot(det_x[:, None] - x[None, :], det_y[:, None] - y[None, :])
    return d.argmin(axis=1), d.min(axis=1) < radius_px


# ----------------------------------------------------------------------------------------------------------------
# the bound itself, against closed forms


def test_crb_matches_closed_forms_for_a_well_sampled_psf():
    """For a PSF much wider than a pixel the bound has closed forms (e.g. Mendez, Silva & Lobos 2013, PASP 125:580,
    eqs. 27 and 30): photon-limited sigma_x^2 = s^2 / N, background-limited sigma_x^2 = 8 pi s^4 B / N^2, with
    s^2 = sigma^2 + 1/12 (a pixel's box adds 1/12 px^2 to the Gaussian's variance). Tolerance 2 %: the residual
    non-Gaussianity of the pixel-integrated profile at sigma = 3 px, and the finite box."""
    sigma = 3.0
    s2 = sigma**2 + 1.0 / 12.0
    n_photons = 1.0e6
    photon, _ = centroid_crb_px(50.3, 60.7, n_photons, sigma, background_e=1e-6, read_noise_e=0.0, gain_e_per_adu=0.0)
    assert photon == pytest.approx(math.sqrt(s2 / n_photons), rel=0.02)
    n_faint, background = 500.0, 1.0e4
    faint, _ = centroid_crb_px(50.3, 60.7, n_faint, sigma, background, read_noise_e=0.0, gain_e_per_adu=0.0)
    assert faint == pytest.approx(math.sqrt(8 * math.pi * s2**2 * background / n_faint**2), rel=0.02)


def test_crb_counts_read_noise_as_extra_background_variance():
    """With Gaussian read noise r the per-pixel variance is mu + r^2: a background B with no read noise and a
    background 0 with read noise sqrt(B) give the same background-limited bound (to 1 %: the faint star's own
    shot noise is the same in both and small)."""
    a, _ = centroid_crb_px(10.2, 10.7, 300.0, 1.2, background_e=100.0, read_noise_e=0.0, gain_e_per_adu=0.0)
    b, _ = centroid_crb_px(10.2, 10.7, 300.0, 1.2, background_e=1e-9, read_noise_e=10.0, gain_e_per_adu=0.0)
    assert a == pytest.approx(b, rel=0.01)


# ----------------------------------------------------------------------------------------------------------------
# accuracy on rendered images


def _rms_over_bound(flux_e: float, seed: int, options: CentroidOptions, frames: int = 4) -> tuple[float, float]:
    """RMS centroid error over the RMS Cramer-Rao bound on ``frames`` rendered frames of 64 isolated stars of
    ``flux_e`` (16-bit ADC: no star saturates), and the mean error (bias) over the RMS error."""
    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(seed)
    errors, bounds = [], []
    for frame in range(frames):
        x, y = _grid_stars(rng)
        rendered = render_stars(x, y, np.full(x.size, flux_e), IMAGE_SIZE, config, seed=100 * seed + frame)
        det = centroid_pixels(rendered.image_adu, options, saturation_adu=config.saturation_adu)
        truth, ok = _match(det.x_px, det.y_px, x, y)
        assert ok.all() and det.x_px.size == x.size  # every star found, no false detection
        errors += [det.x_px - x[truth], det.y_px - y[truth]]
        bounds += [
            centroid_crb_px(
                x[k],
                y[k],
                flux_e,
                config.psf_sigma_px,
                config.background_e,
                config.read_noise_e,
                config.gain_e_per_adu,
            )
            for k in truth
        ]
    errors = np.concatenate(errors)
    rms = float(np.sqrt(np.mean(errors**2)))
    return rms / float(np.sqrt(np.mean(np.square(bounds)))), float(np.mean(errors)) * math.sqrt(errors.size) / rms


@pytest.mark.parametrize("flux_e", [1500.0, 4000.0, 30000.0])
def test_centroid_rms_error_is_within_1_2_of_the_cramer_rao_bound(flux_e):
    """Peak SNR 15, 40 and 250: from background-limited to the star's own shot noise dominating."""
    ratio, bias_sigmas = _rms_over_bound(flux_e, 11, CentroidOptions(gain_e_per_adu=RenderConfig().gain_e_per_adu))
    # 512 samples: the RMS itself scatters by 1 / sqrt(2 * 512) = 3 %, so 0.85 is 5 sigma below the bound (a result
    # below it would mean the truth leaked into the estimate) and 1.2 is the acceptance
    assert 0.85 < ratio < 1.2, ratio
    # no bias from the pixel convention: (0, 0) is the centre of the first pixel (a half-pixel slip shows here)
    assert abs(bias_sigmas) < 4


def test_windowed_centroid_alone_loses_to_the_psf_fit_where_shot_noise_dominates():
    """SEP's windowed centroid (window = PSF) is the matched filter: maximum likelihood where background noise
    dominates, but its linearised variance in the photon limit is E[w x^2 I] / (E[w I] - E[w x^2 I] / s^2)^2 =
    16 s^2 / 9 N, (4/3)^2 x the bound. At 30000 e- (peak SNR 250, between the regimes) it lies between 1 and 4/3
    (+5 %: sampling scatter of 384 samples), where the PSF fit reaches the bound (test above)."""
    window, _ = _rms_over_bound(30000.0, 5, CentroidOptions(method="window"), frames=3)
    assert 1.05 < window < 4.0 / 3.0 * 1.05, window


def test_psf_model_jacobian_matches_finite_differences():
    """The analytic derivatives behind the fit and the bound (hostlink.sky.render.pixel_integrated_gaussian_dsource)
    against central differences of the model. Tolerance 1e-8 of the flux: with a 1e-5 px step the truncation error
    is ~N h^2 / sigma^3 ~ 2e-7 and the rounding error ~eps N / h ~ 3e-8, both far below; flux and background enter
    linearly (exact differences)."""
    from hostlink.images.centroid import psf_model

    cols, rows = np.arange(3.0, 14.0), np.arange(5.0, 16.0)
    params = np.array([8.3, 10.6, 2500.0, 12.0])
    _, jac = psf_model(cols, rows, params, 1.1)
    for k, step in enumerate([1e-5, 1e-5, 1e-2, 1e-2]):
        dp = np.zeros(4)
        dp[k] = step
        numeric = (psf_model(cols, rows, params + dp, 1.1)[0] - psf_model(cols, rows, params - dp, 1.1)[0]) / (2 * step)
        np.testing.assert_allclose(jac[..., k], numeric, rtol=0, atol=1e-8 * params[2])


def test_the_batched_psf_fit_reaches_scipys_least_squares_minimum():
    """The PSF fit runs every star of a frame at once (numpy Levenberg-Marquardt); checked against scipy's MINPACK
    Levenberg-Marquardt (scipy.optimize.least_squares, method 'lm', its tolerances at 1e-12) fitting the same model
    (:func:`psf_model`) to the same pixels, star by star: the same minimum to 1e-5 px (both stop where the cost no
    longer falls; the centroid noise here is ~0.05 px, so the difference is nothing). The batch model equals the
    single-star model to rounding."""
    from scipy.optimize import least_squares

    from hostlink.images.centroid import _psf_fit_centroids, psf_model, psf_model_batch

    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(21)
    x, y = _grid_stars(rng)
    rendered = render_stars(x, y, np.full(x.size, 3000.0), IMAGE_SIZE, config, seed=5)
    image = rendered.image_adu - np.median(rendered.image_adu)
    rms = np.full(image.shape, float(np.std(image[image < np.percentile(image, 90)])))
    start_x, start_y = x + rng.uniform(-0.3, 0.3, x.size), y + rng.uniform(-0.3, 0.3, x.size)
    sigma = config.psf_sigma_px
    fx, fy, fitted = _psf_fit_centroids(image, rms, start_x, start_y, sigma, None)
    assert fitted.all()

    half = int(math.ceil(3.0 * sigma)) + 1
    for k in range(x.size):
        c, r = int(round(start_x[k])), int(round(start_y[k]))
        cols, rows = np.arange(c - half, c + half + 1, dtype=float), np.arange(r - half, r + half + 1, dtype=float)
        data = image[r - half : r + half + 1, c - half : c + half + 1]
        p0 = np.array([start_x[k], start_y[k], max(float(np.sum(data - np.median(data))), 1.0), np.median(data)])
        mu_single, jac_single = psf_model(cols, rows, p0, sigma)
        mu_batch, jac_batch = psf_model_batch(cols[None], rows[None], p0[None], sigma)
        np.testing.assert_allclose(mu_batch[0], mu_single, rtol=1e-12)  # the same products, in another order
        np.testing.assert_allclose(jac_batch[0], jac_single, rtol=1e-12, atol=1e-12 * p0[2])
        fit = least_squares(
            lambda p, c, r, d: (psf_model(c, r, p, sigma)[0] - d).ravel(),
            p0,
            jac=lambda p, c, r, d: psf_model(c, r, p, sigma)[1].reshape(-1, 4),
            args=(cols, rows, data),
            method="lm",
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
        )
        assert abs(fit.x[0] - fx[k]) < 1e-5 and abs(fit.x[1] - fy[k]) < 1e-5, (k, fit.x[:2], fx[k], fy[k])


def test_a_singular_stamp_in_the_batch_is_flagged_and_the_others_solved_as_on_their_own():
    """The fit's batched step (:func:`_solve_each`): numpy refuses a whole batch for one singular system; the
    singular ones (here two, one at an end) are flagged with a zero step, and every other system gets exactly the
    solution numpy gives it alone (the same LAPACK call: bit for bit)."""
    from hostlink.images.centroid import _solve_each

    rng = np.random.default_rng(3)
    a = rng.normal(size=(9, 4, 4)) + 4.0 * np.eye(4)
    b = rng.normal(size=(9, 4))
    a[2, :, 1] = 0.0  # a column of zeros: an exact zero pivot
    a[8] = 0.0
    x, singular = _solve_each(a, b)
    assert singular.tolist() == [k in (2, 8) for k in range(9)]
    assert np.all(x[singular] == 0.0)
    for k in np.flatnonzero(~singular):
        assert np.array_equal(x[k], np.linalg.solve(a[k], b[k]))


# ----------------------------------------------------------------------------------------------------------------
# rejections


def test_hot_pixels_and_saturated_stars_are_rejected_and_counted_and_blended_pairs_flagged():
    """Hot pixels and (with ``keep_saturated`` False) saturated stars are rejected and counted; equal pairs 2.5-5 px
    apart (2-4 PSF sigmas) are kept, flagged as blends (``blended``, counted in ``blended_kept``), each with a
    ``sigma_px`` that holds the bound on its bias: the error of each, a shift towards its companion, is within
    sqrt(2) x its ``sigma_px`` (the bound b enters per axis as b / sqrt(2); measured at most 1.37 x), while the
    isolated stars are kept unflagged."""
    config = RenderConfig(hot_pixels=30)
    rng = np.random.default_rng(2)
    x, y = _grid_stars(rng)
    flux = np.full(x.size, 3000.0)
    flux[:8] = 3.0e5  # the first row saturates
    pairs = np.arange(48, 64)  # the last two rows get an equal companion 2.5 to 5 px away (2 to 4 PSF sigmas)
    companion_x = x[pairs] + np.linspace(2.5, 5.0, pairs.size)
    all_x = np.concatenate([x, companion_x])
    all_y = np.concatenate([y, y[pairs]])
    all_flux = np.concatenate([flux, np.full(pairs.size, 3000.0)])
    rendered = render_stars(all_x, all_y, all_flux, IMAGE_SIZE, config, seed=3)
    assert rendered.saturated.sum() == 8
    options = CentroidOptions(gain_e_per_adu=config.gain_e_per_adu, keep_saturated=False)
    det = centroid_pixels(rendered.image_adu, options, saturation_adu=config.saturation_adu)
    report = det.report
    assert report.rejected_saturated == 8
    # a hot pixel falling on a star's footprint becomes part of that star, so not all 30 are separate detections
    on_star = np.min(np.hypot(*(rendered.hot_pixels_xy[:, None, :] - np.c_[all_x, all_y][None]).transpose(2, 0, 1)), 1)
    assert report.rejected_hot == int(np.sum(on_star > 4 * config.psf_sigma_px))
    truth, ok = _match(det.x_px, det.y_px, all_x, all_y)
    assert ok.all()  # every kept detection is a star or a pair (no hot pixel kept)
    flagged = det.blended
    assert set(truth[~flagged].tolist()) == set(range(8, 48))  # every isolated star kept, none flagged
    in_pairs = set(pairs.tolist()) | set(range(x.size, all_x.size))
    assert set(truth[flagged].tolist()) <= in_pairs and report.blended_kept == int(flagged.sum())
    assert int(flagged.sum()) >= pairs.size  # each pair: one merged blob, or two deblended parts
    error = np.hypot(det.x_px - all_x[truth], det.y_px - all_y[truth])
    assert np.all(error[flagged] <= math.sqrt(2.0) * det.sigma_px[flagged])


def test_unresolved_pairs_closer_than_the_deblender_splits_are_flagged_with_their_bias_in_sigma_px():
    """Two equal stars 2 px (1.7 sigma) apart have no saddle between them: SEP sees one peak. Their windowed second
    moments are elongated (ellipticity ~0.2) far beyond the frame's PSF (its single stars: ~0.02): each pair is kept
    as one star, flagged as a blend, its ``sigma_px`` holding the bound on its centroid's bias (the pair's centre lies
    1 px from either star: within sqrt(2) x ``sigma_px``, the bound's per-axis share). Single stars at the same flux:
    none flagged (4 sigma: a false flag per 3000 stars)."""
    config = RenderConfig(hot_pixels=0)
    rng = np.random.default_rng(4)
    x, y = _grid_stars(rng)
    paired = np.arange(0, x.size, 4)  # every fourth star gets a companion 2 px to its right
    all_x = np.concatenate([x, x[paired] + 2.0])
    all_y = np.concatenate([y, y[paired]])
    rendered = render_stars(all_x, all_y, np.full(all_x.size, 3000.0), IMAGE_SIZE, config, seed=9)
    det = centroid_pixels(rendered.image_adu, CentroidOptions(gain_e_per_adu=2.0), saturation_adu=4095)
    truth, ok = _match(det.x_px, det.y_px, all_x, all_y)
    assert ok.all() and det.x_px.size == x.size  # one centroid per single star and per pair
    singles = np.setdiff1d(np.arange(x.size), paired)
    assert set(truth[~det.blended].tolist()) == set(singles.tolist())  # every single kept, unflagged
    assert det.report.blended_kept == paired.size and det.report.rejected_blended == 0
    error = np.hypot(det.x_px - all_x[truth], det.y_px - all_y[truth])
    assert np.all(error[det.blended] > 0.5)  # the pair's centroid is not a star's: the flag is needed
    assert np.all(error[det.blended] <= math.sqrt(2.0) * det.sigma_px[det.blended])


def test_an_elliptical_psf_common_to_the_frame_is_not_a_blend():
    """A real lens's PSF is elliptical (here sigma 1.4 x 1.0 px, ellipticity 0.32: coma or astigmatism). Every star
    of the frame shares it, so none stands out as a blend and all are kept."""
    from hostlink.sky.render import pixel_integrated_gaussian

    rng = np.random.default_rng(6)
    x, y = _grid_stars(rng)
    image = np.full(IMAGE_SIZE[::-1], 100.0)
    for xs, ys in zip(x, y, strict=True):
        cols, rows = np.arange(int(xs) - 8, int(xs) + 9), np.arange(int(ys) - 8, int(ys) + 9)
        star = 3000.0 * np.outer(pixel_integrated_gaussian(rows, ys, 1.0), pixel_integrated_gaussian(cols, xs, 1.4))
        image[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1] += star
    image = rng.poisson(image).astype(float)
    det = centroid_pixels(image, CentroidOptions())
    assert det.report.rejected_blended == 0 and det.report.kept == x.size


def test_a_given_dark_frame_is_subtracted_first_and_must_match_in_size():
    from hostlink.errors import UserError

    config = RenderConfig(hot_pixels=0, background_e=0.0)
    rng = np.random.default_rng(8)
    x, y = _grid_stars(rng, n_side=4, spacing_px=100.0)
    rendered = render_stars(x, y, np.full(x.size, 4000.0), IMAGE_SIZE, config, seed=1)
    pattern = np.zeros(IMAGE_SIZE[::-1])
    pattern[::37, ::41] = 900.0  # a fixed pattern of bright pixels the dark frame knows
    image = rendered.image_adu + pattern
    with_dark = centroid_pixels(image, CentroidOptions(), background=pattern)
    assert with_dark.report.kept == x.size and with_dark.report.rejected_hot == 0
    without = centroid_pixels(image, CentroidOptions())
    assert without.report.rejected_hot > 0  # the pattern's spikes are seen, and rejected as hot pixels
    with pytest.raises(UserError, match="background frame is 10 x 10 px"):
        centroid_pixels(image, CentroidOptions(), background=np.zeros((10, 10)))


def test_clipped_correlated_noise_of_an_8_bit_colour_camera_gives_few_false_stars():
    """An 8-bit camera whose black level sits below zero (60 % of the pixels read 0) and whose demosaicing
    correlates neighbouring pixels (as the real frames in docs: SEP alone estimates 1.2 ADU of noise where the
    filtered image shows 3.4): the noise map is rescaled to what the detection filter sees, so the default 5 sigma
    keeps its meaning. Tolerance: at most 5 false detections on 1.3 Mpx (a Gaussian 5 sigma gives < 1; the clipped
    tail is heavier)."""
    from scipy import ndimage

    from hostlink.sky.render import pixel_integrated_gaussian

    rng = np.random.default_rng(12)
    height, width = 1000, 1300
    noise = ndimage.convolve(rng.normal(0.0, 5.0, (height, width)), np.full((2, 2), 0.5))  # correlated, sigma 5
    gx, gy = np.meshgrid(np.arange(10), np.arange(8))
    x = 60.0 + 125.0 * gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    y = 60.0 + 120.0 * gy.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    stars = np.zeros((height, width))
    for xs, ys in zip(x, y, strict=True):
        cols, rows = np.arange(int(xs) - 5, int(xs) + 6), np.arange(int(ys) - 5, int(ys) + 6)
        psf = np.outer(pixel_integrated_gaussian(rows, ys, 0.8), pixel_integrated_gaussian(cols, xs, 0.8))
        stars[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1] += 600.0 * psf  # peak ~130 ADU
    image = np.clip(np.round(stars + noise - 2.0), 0, 255).astype(np.uint8)
    assert np.mean(image == 0) > 0.55  # the black level clips more than half of the pixels
    det = centroid_pixels(image, CentroidOptions(), saturation_adu=255)
    truth, ok = _match(det.x_px, det.y_px, x, y)
    assert set(truth[ok].tolist()) == set(range(x.size))  # every star found
    assert np.sum(~ok) <= 5


def test_saturated_stars_can_be_kept_ranked_first_with_a_windowed_centroid():
    """With keep_saturated the clipped stars stay (for cameras whose brightest stars always saturate): first in the
    brightness order, centroided by the window (symmetric about the star even with a flat-topped core). Tolerance
    0.15 px: measured <= 0.064 px for these 100x-saturated stars (a clipped core holds less position information
    than an unclipped star's bound), with room for other noise draws."""
    config = RenderConfig(hot_pixels=0)
    rng = np.random.default_rng(7)
    x, y = _grid_stars(rng)
    flux = np.full(x.size, 3000.0)
    flux[:8] = 3.0e5
    rendered = render_stars(x, y, flux, IMAGE_SIZE, config, seed=4)
    options = CentroidOptions(gain_e_per_adu=2.0, keep_saturated=True)
    det = centroid_pixels(rendered.image_adu, options, saturation_adu=config.saturation_adu)
    assert det.report.saturated_kept == 8 and det.report.rejected_saturated == 0 and det.report.kept == x.size
    truth, ok = _match(det.x_px, det.y_px, x, y)
    assert ok.all()
    assert set(truth[:8].tolist()) == set(range(8))  # the saturated stars rank first
    assert np.all(np.hypot(det.x_px[:8] - x[truth[:8]], det.y_px[:8] - y[truth[:8]]) < 0.15)
    # flagged, with the saturated floor as their noise (their clipped core carries no PSF-fit information)
    assert det.saturated[:8].all() and not det.saturated[8:].any()
    assert np.all(det.sigma_px[:8] >= SATURATED_SIGMA_PX)


def test_saturated_stars_are_kept_by_default():
    """The brightest stars of a frame are the anchors of identification: kept unless asked otherwise."""
    assert CentroidOptions().keep_saturated


@pytest.mark.parametrize("flux_e", [1500.0, 30000.0])
def test_sigma_px_is_each_stars_cramer_rao_bound_and_the_scatter_it_predicts(flux_e):
    """The ``sigma_px`` written per star is the Cramer-Rao bound computed from the truth (true flux, the render's
    background, read noise and gain: :func:`centroid_crb_px`): the median ratio within 5 % and every star within
    15 % (the star's flux and the local noise are estimated from the one image: at 1500 e- the flux to ~3 %, and
    the background-limited bound goes as 1 / flux, so 15 % is 5 sigma); and the centroid errors it predicts are the
    errors measured: their RMS in units of each star's own sigma_px is 1 within 0.85-1.2 (the PSF fit's measured
    efficiency, 0.99-1.08, plus the 3.6 % sampling scatter of 384 samples). Sparse frames (16 stars on 512 x 512
    px): the frame's noise is measured on pixels the stars leave alone."""
    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(17)
    normalised, ratio = [], []
    for frame in range(12):
        x, y = _grid_stars(rng, n_side=4, spacing_px=120.0)
        rendered = render_stars(x, y, np.full(x.size, flux_e), IMAGE_SIZE, config, seed=300 + frame)
        det = centroid_pixels(rendered.image_adu, CentroidOptions(gain_e_per_adu=config.gain_e_per_adu))
        truth, ok = _match(det.x_px, det.y_px, x, y)
        assert ok.all() and det.x_px.size == x.size
        bound = np.array(
            [
                max(
                    centroid_crb_px(
                        x[k],
                        y[k],
                        flux_e,
                        config.psf_sigma_px,
                        config.background_e,
                        config.read_noise_e,
                        config.gain_e_per_adu,
                    )
                )
                for k in truth
            ]
        )
        ratio.append(det.sigma_px / bound)
        normalised += [(det.x_px - x[truth]) / det.sigma_px, (det.y_px - y[truth]) / det.sigma_px]
    ratio = np.concatenate(ratio)
    assert abs(float(np.median(ratio)) - 1.0) < 0.05, float(np.median(ratio))
    assert np.all(np.abs(np.percentile(ratio, [2.5, 97.5]) - 1.0) < 0.15), (ratio.min(), ratio.max())
    rms = float(np.sqrt(np.mean(np.concatenate(normalised) ** 2)))
    assert 0.85 < rms < 1.2, rms


@pytest.mark.parametrize("psf_sigma_px", [0.55, 0.77])
def test_sharp_stars_pass_the_hot_pixel_test_and_hot_pixels_do_not(psf_sigma_px):
    """Sharp stars (PSF sigma 0.55 and 0.77 px: the central pixel holds 30-50 % of the flux, its 4 neighbours on
    average 0.3-0.5 of the peak, down to 0.2 at a pixel corner with noise) from peak SNR ~8 to ~200, among 30 hot
    pixels: no star is lost to the hot-pixel test (every star kept without the test is kept with it), no hot pixel
    is kept, and every hot pixel that is not on a star is rejected and counted as hot."""
    config = RenderConfig(hot_pixels=30, psf_sigma_px=psf_sigma_px, bits=16)
    rng = np.random.default_rng(23)
    x, y = _grid_stars(rng)
    flux = np.geomspace(400.0, 40000.0, x.size)
    rendered = render_stars(x, y, flux, IMAGE_SIZE, config, seed=9)
    options = CentroidOptions(gain_e_per_adu=config.gain_e_per_adu)
    det = centroid_pixels(rendered.image_adu, options)
    untested = centroid_pixels(rendered.image_adu, replace(options, hot_pixel_chi2=math.inf))
    truth, ok = _match(det.x_px, det.y_px, x, y)
    truth_untested, ok_untested = _match(untested.x_px, untested.y_px, x, y)
    on_star = np.min(np.hypot(*(rendered.hot_pixels_xy[:, None, :] - np.c_[x, y][None]).transpose(2, 0, 1)), 1)
    assert ok.all()  # no hot pixel kept
    assert np.count_nonzero(ok_untested) >= 0.85 * x.size  # the stars are there to be lost
    assert set(truth.tolist()) == set(truth_untested[ok_untested].tolist())  # and none is lost to the test
    # a hot pixel at the border too: the test's box lies inside the image, the spike where the pixel is
    border = np.any((rendered.hot_pixels_xy < 2) | (rendered.hot_pixels_xy > np.array(IMAGE_SIZE) - 3), axis=1)
    assert det.report.rejected_hot == int(np.sum(on_star > 4 * psf_sigma_px)) and det.report.rejected_edge == 0
    assert psf_sigma_px != 0.55 or border.any()  # the draw puts one there


def _elliptical_star(
    image: np.ndarray, xs: float, ys: float, flux: float, sigma_major: float, sigma_minor: float, angle_rad: float
) -> None:
    """Add a star with an elliptical Gaussian PSF (major axis at ``angle_rad`` from x), integrated over each pixel
    by 7 x 7 sub-pixel samples."""
    sub = (np.arange(7) + 0.5) / 7 - 0.5
    c0, r0 = int(xs) - 10, int(ys) - 10
    cols = (np.arange(c0, c0 + 21)[:, None] + sub[None, :]).ravel()
    rows = (np.arange(r0, r0 + 21)[:, None] + sub[None, :]).ravel()
    dx, dy = cols[None, :] - xs, rows[:, None] - ys
    u = dx * math.cos(angle_rad) + dy * math.sin(angle_rad)
    v = -dx * math.sin(angle_rad) + dy * math.cos(angle_rad)
    density = np.exp(-0.5 * ((u / sigma_major) ** 2 + (v / sigma_minor) ** 2)) / (
        2 * math.pi * sigma_major * sigma_minor
    )
    pixels = density.reshape(21, 7, 21, 7).mean(axis=(1, 3))
    image[r0 : r0 + 21, c0 : c0 + 21] += flux * pixels


def test_a_psf_elongated_towards_the_field_edge_is_not_a_blend_but_a_pair_still_is():
    """A wide lens's PSF is elongated radially off axis (here sigma 1.0 px at the centre growing to 1.0 x 1.6 px,
    ellipticity 0.44, at the corners: as on the 27-deg granasat frames, where the frame's median PSF rejected 30 of
    the stars the plate solver names as blends). Compared with the PSF of its own part of the field, no single star
    is flagged; an equal pair 2 px apart near the centre (ellipticity ~0.2 beyond the PSF's there) still is."""
    rng = np.random.default_rng(13)
    x, y = _grid_stars(rng)
    image = np.full(IMAGE_SIZE[::-1], 100.0)
    centre = 0.5 * (np.array(IMAGE_SIZE) - 1)
    corner = float(np.hypot(*centre))
    near = np.hypot(x - centre[0], y - centre[1]) < 120.0
    paired = np.flatnonzero(near)[::2]
    for k, (xs, ys) in enumerate(zip(x, y, strict=True)):
        r = math.hypot(xs - centre[0], ys - centre[1])
        angle = math.atan2(ys - centre[1], xs - centre[0])
        _elliptical_star(image, xs, ys, 3000.0, 1.0 + 0.6 * (r / corner) ** 2, 1.0, angle)
        if k in paired:
            _elliptical_star(image, xs + 2.0, ys, 3000.0, 1.0 + 0.6 * (r / corner) ** 2, 1.0, angle)
    image = rng.poisson(image).astype(float)
    det = centroid_pixels(image, CentroidOptions(gain_e_per_adu=1.0))
    singles = np.setdiff1d(np.arange(x.size), paired)
    truth, ok = _match(det.x_px, det.y_px, x, y)
    assert ok.all()
    assert set(truth[~det.blended].tolist()) == set(singles.tolist())  # every single kept, at the corners too
    assert paired.size >= 2 and det.report.blended_kept == paired.size  # each pair kept once, flagged


def test_stars_cut_by_the_border_are_fitted_on_the_pixels_they_have():
    """A star whose centre lies 2-3.5 px inside the border (SEP flags its footprint as truncated) is kept: the PSF fit
    uses the pixels inside the image, which the model describes as well as any others, so its centroid is unbiased.
    Errors within 5 x the Cramer-Rao bound of a complete star (the lost pixels carry up to half of its information
    along x; measured at most 0.058 px, 1.9 x the bound: no sign of a bias from the cut, which would show as errors of
    one sign)."""
    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(23)
    y = np.linspace(40.0, 470.0, 8) + rng.uniform(-0.5, 0.5, 8)
    x = rng.uniform(2.0, 3.5, 8)  # the left border (column 0 the first); the hot-pixel test needs 2 columns beside
    rendered = render_stars(x, y, np.full(x.size, 4000.0), IMAGE_SIZE, config, seed=8)
    det = centroid_pixels(rendered.image_adu, CentroidOptions(gain_e_per_adu=config.gain_e_per_adu))
    truth, ok = _match(det.x_px, det.y_px, x, y)
    assert ok.all() and set(truth.tolist()) == set(range(x.size)) and det.report.rejected_edge == 0
    bound = max(
        centroid_crb_px(
            20.3, 20.6, 4000.0, config.psf_sigma_px, config.background_e, config.read_noise_e, config.gain_e_per_adu
        )
    )
    assert np.all(np.hypot(det.x_px - x[truth], det.y_px - y[truth]) < 5 * bound), (det.x_px - x[truth], bound)


def test_a_frame_computed_in_blocks_of_stars_gives_the_same_stars(monkeypatch):
    """The per-frame computations (PSF fit, fluxes, sigma_px, the blend test's moments) run over blocks of stars
    bounded in memory (a defocused or crowded frame): with blocks of a few stars each the result is the same, to
    the last bit (each star's computation is its own)."""
    from hostlink.images import centroid

    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(29)
    x, y = _grid_stars(rng)
    rendered = render_stars(x, y, rng.uniform(2000.0, 20000.0, x.size), IMAGE_SIZE, config, seed=4)
    options = CentroidOptions(gain_e_per_adu=config.gain_e_per_adu)
    whole = centroid_pixels(rendered.image_adu, options)
    monkeypatch.setattr(centroid, "_STAMP_BUDGET_PX", 1000)  # 1 to 5 stars per block
    blocks = centroid_pixels(rendered.image_adu, options)
    assert whole.x_px.size == x.size
    for name in ("x_px", "y_px", "flux_adu", "sigma_px"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))


def test_stars_within_two_pixels_of_the_border_are_kept_saturated_or_not():
    """Stars whose centre lies 0.3-2 px from the border (half of them saturated), beside a grid of interior stars
    that gives the frame's PSF: every one kept, none rejected at the edge. An unsaturated one is fitted on the pixels
    it has and its ``sigma_px`` is the bound over those pixels (errors within 4 of them: a 2-D error beyond 4 per-axis
    sigmas has probability exp(-8) = 3e-4; measured at most 2.97). A saturated one is centroided by the window over
    the part of its image point-symmetric about its centre (the missing side biases nothing): errors within its
    ``sigma_px``, the saturated floor over the root of the share of the window it used (measured at most 0.69 of
    it, 0.23 px)."""
    config = RenderConfig(hot_pixels=0, bits=16)
    rng = np.random.default_rng(31)
    grid_x, grid_y = _grid_stars(rng)
    n = 16
    border_y = np.linspace(40.0, 470.0, n) + rng.uniform(-0.5, 0.5, n)
    border_x = rng.uniform(0.3, 2.0, n)
    flux = np.concatenate([np.full(grid_x.size, 4000.0), np.where(np.arange(n) % 2 == 0, 4000.0, 3.0e6)])
    x, y = np.concatenate([grid_x, border_x]), np.concatenate([grid_y, border_y])
    rendered = render_stars(x, y, flux, IMAGE_SIZE, config, seed=8)
    options = CentroidOptions(gain_e_per_adu=config.gain_e_per_adu)
    det = centroid_pixels(rendered.image_adu, options, saturation_adu=config.saturation_adu)
    truth, ok = _match(det.x_px, det.y_px, x, y)
    assert ok.all() and set(truth.tolist()) == set(range(x.size)) and det.report.rejected_edge == 0
    at_border = truth >= grid_x.size
    error = np.hypot(det.x_px - x[truth], det.y_px - y[truth])
    clipped = at_border & det.saturated
    assert clipped.sum() == n // 2 and np.all(error[clipped] < det.sigma_px[clipped])
    fitted = at_border & ~det.saturated
    assert np.all(error[fitted] < 4.0 * det.sigma_px[fitted])


def test_hot_pixels_at_the_clip_level_are_rejected_and_sharp_saturated_stars_kept():
    """An 8-bit camera clips a hot pixel at 255, where the likelihood test cannot judge it (a clipped pixel is a lower
    bound). Sharp stars (PSF sigma 0.77 px, as the 35 mm lens on 6.9 um pixels), 62 of 64 saturated, most with a
    single clipped pixel, beside 30 hot pixels all at 255: every hot pixel rejected and counted as hot (they were kept
    as the frame's brightest "stars"), every star kept (its edge neighbours hold at least 0.18 of its clipped peak,
    the least a star of sigma 0.45 px puts there; a hot pixel's hold noise)."""
    config = RenderConfig(psf_sigma_px=0.77, hot_pixels=30, bits=8)
    rng = np.random.default_rng(41)
    x, y = _grid_stars(rng)
    rendered = render_stars(x, y, np.geomspace(1500.0, 3.0e5, x.size), IMAGE_SIZE, config, seed=12)
    hx, hy = rendered.hot_pixels_xy.T
    assert np.all(rendered.image_adu[hy, hx] == config.saturation_adu) and rendered.saturated.sum() == 62
    options = CentroidOptions(gain_e_per_adu=config.gain_e_per_adu)
    det = centroid_pixels(rendered.image_adu, options, saturation_adu=config.saturation_adu)
    truth, ok = _match(det.x_px, det.y_px, x, y)
    on_star = np.min(np.hypot(*(rendered.hot_pixels_xy[:, None, :] - np.c_[x, y][None]).transpose(2, 0, 1)), 1)
    assert ok.all() and set(truth.tolist()) == set(range(x.size))  # no hot pixel kept, every star kept
    assert det.report.rejected_hot == int(np.sum(on_star > 4 * config.psf_sigma_px))


def test_the_bound_without_shot_noise_from_row_and_column_sums_is_the_pixel_sums():
    """Without the gain every pixel's variance is the star's measured noise, and the Fisher matrix of the separable
    PSF model is a product of row and column sums (psf._crb_max_separable): the same bound as the sums over the
    box's pixels, stars cut by the border included, to rounding (1e-12 relative; measured 2e-14)."""
    from hostlink.images.centroid.psf import _crb_max_block, _crb_max_separable

    rng = np.random.default_rng(17)
    n = 300
    x, y = rng.uniform(-0.4, 69.4, n), rng.uniform(-0.4, 49.4, n)  # an image of 70 x 50 px, many cut by its border
    flux, noise = 10 ** rng.uniform(2.0, 6.0, n), rng.uniform(1.0, 20.0, n)
    for sigma in (0.45, 0.9, 1.5, 3.0):
        half = int(math.ceil(6 * sigma) + 2)
        for shape in ((50, 70), None):
            pixel_sums = _crb_max_block(x, y, flux, sigma, noise, False, half, shape)
            separable = _crb_max_separable(x, y, flux, sigma, noise, False, half, shape)
            np.testing.assert_allclose(separable, pixel_sums, rtol=1e-12)


def test_hot_pixels_at_the_clip_level_are_counted_as_hot_when_saturated_stars_are_rejected():
    """The frame of the test above with ``keep_saturated=False`` (``--reject-saturated``): each detection is counted
    once, by its cause. The clipped hot pixels are counted as hot, as when saturated stars are kept (they were counted
    as saturated stars: 30 hot pixels as 0 hot and 93 saturated), and the saturated count is the saturated stars that
    the default keeps."""
    config = RenderConfig(psf_sigma_px=0.77, hot_pixels=30, bits=8)
    rng = np.random.default_rng(41)
    x, y = _grid_stars(rng)
    rendered = render_stars(x, y, np.geomspace(1500.0, 3.0e5, x.size), IMAGE_SIZE, config, seed=12)
    on_star = np.min(np.hypot(*(rendered.hot_pixels_xy[:, None, :] - np.c_[x, y][None]).transpose(2, 0, 1)), 1)
    reports = [
        centroid_pixels(
            rendered.image_adu,
            CentroidOptions(gain_e_per_adu=config.gain_e_per_adu, keep_saturated=keep),
            saturation_adu=config.saturation_adu,
        ).report
        for keep in (True, False)
    ]
    kept, rejecting = reports
    assert rejecting.rejected_hot == kept.rejected_hot == int(np.sum(on_star > 4 * config.psf_sigma_px))
    assert rejecting.rejected_saturated == kept.saturated_kept and rejecting.saturated_kept == 0
    causes = ("rejected_hot", "rejected_saturated", "rejected_blended", "rejected_edge", "rejected_no_flux")
    assert rejecting.kept + sum(getattr(rejecting, c) for c in causes) == rejecting.detected
