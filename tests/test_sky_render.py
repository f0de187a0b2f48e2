"""The image renderer for tests (hostlink.sky.render): the simulator's stars drawn through the true camera with a
pixel-integrated Gaussian PSF, shot and read noise, hot pixels and saturation, seeded, with the truth."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.images.centroid import CentroidOptions, centroid_pixels
from hostlink.sky.render import RenderConfig, expected_electrons, render_frame, render_stars
from hostlink.sky.simulate import SimConfig, seed004_camera, simulate


@pytest.fixture(scope="module")
def sim():
    """Two noiseless frames of the real sky through seed 004's camera (10 deg field), every star to Hp 7."""
    return simulate(SimConfig(camera=seed004_camera(), frames=2, noise_px=0.0, min_stars=5, max_stars=500, maglim=7.0))


def test_truth_is_the_simulated_projection_and_flux_follows_magnitude(sim):
    config = RenderConfig()
    frame = render_frame(sim, 1, config)
    rows = (sim.session.frame == 1) & (sim.session.star_id != 0)
    np.testing.assert_array_equal(frame.truth_x_px, sim.session.x_px[rows])
    np.testing.assert_array_equal(frame.truth_y_px, sim.session.y_px[rows])
    np.testing.assert_array_equal(frame.truth_star_id, sim.session.star_id[rows])
    np.testing.assert_allclose(frame.truth_flux_e, config.zero_point_e * 10 ** (-0.4 * sim.session.mag[rows]))
    assert frame.image_adu.shape == (1024, 1024) and frame.image_adu.dtype == np.uint16


def test_render_is_deterministic_for_a_seed(sim):
    a = render_frame(sim, 0, RenderConfig(seed=7))
    b = render_frame(sim, 0, RenderConfig(seed=7))
    c = render_frame(sim, 0, RenderConfig(seed=8))
    np.testing.assert_array_equal(a.image_adu, b.image_adu)
    assert np.any(a.image_adu != c.image_adu)


def test_noiseless_model_holds_every_electron_of_an_interior_star():
    config = RenderConfig(background_e=0.0)
    mu = expected_electrons(np.array([40.3]), np.array([31.8]), np.array([12345.0]), (80, 64), config)
    # the +-6 sigma box misses < 2e-9 of a Gaussian's flux
    assert mu.sum() == pytest.approx(12345.0, rel=1e-8)
    # pixel-centre convention: the first moment of the drawn light is the star's position
    rows, cols = np.mgrid[0:64, 0:80]
    assert (mu * cols).sum() / mu.sum() == pytest.approx(40.3, abs=1e-6)
    assert (mu * rows).sum() / mu.sum() == pytest.approx(31.8, abs=1e-6)


def test_background_noise_is_shot_plus_read_plus_quantisation():
    config = RenderConfig(background_e=200.0, read_noise_e=6.0, gain_e_per_adu=2.0, bias_adu=100.0, hot_pixels=0)
    frame = render_stars(np.zeros(0), np.zeros(0), np.zeros(0), (400, 400), config, seed=3)
    counts = frame.image_adu.astype(np.float64)
    expected_var = (200.0 + 6.0**2) / 2.0**2 + 1.0 / 12.0  # [ADU^2]: Poisson + read, over gain^2, + rounding
    # 160000 samples: the mean is known to 0.02 ADU and the variance to 0.4 % (1 sigma); tolerances are 5 sigma
    assert counts.mean() == pytest.approx(100.0 + 200.0 / 2.0, abs=0.1)
    assert counts.var() == pytest.approx(expected_var, rel=0.02)


def test_saturated_stars_are_flagged_and_clipped_at_full_scale():
    config = RenderConfig(hot_pixels=0)
    frame = render_stars(np.array([30.0, 90.0]), np.array([30.0, 30.0]), np.array([5.0e5, 3.0e3]), (128, 64), config)
    np.testing.assert_array_equal(frame.saturated, [True, False])
    assert frame.image_adu[30, 30] == config.saturation_adu
    assert frame.image_adu.max() == config.saturation_adu


def test_hot_pixels_are_single_pixels_at_their_listed_places():
    config = RenderConfig(hot_pixels=5, hot_pixel_e=6000.0, background_e=10.0)
    frame = render_stars(np.zeros(0), np.zeros(0), np.zeros(0), (64, 64), config, seed=1)
    cols, rows = frame.hot_pixels_xy.T
    # 6000 e- at gain 2 is 3000 ADU above a background of a few ADU
    assert np.all(frame.image_adu[rows, cols] > 2500)
    assert np.sum(frame.image_adu > 2500) == np.unique(frame.hot_pixels_xy, axis=0).shape[0]


def test_mirrored_detector_reverses_columns_in_image_and_truth(sim):
    normal = render_frame(sim, 0, RenderConfig(hot_pixels=0))
    mirrored = render_frame(sim, 0, RenderConfig(hot_pixels=0), mirrored=True)
    np.testing.assert_allclose(mirrored.truth_x_px, 1023 - normal.truth_x_px)
    np.testing.assert_array_equal(mirrored.truth_y_px, normal.truth_y_px)
    det = centroid_pixels(mirrored.image_adu, CentroidOptions(gain_e_per_adu=2.0), saturation_adu=4095)
    d = np.hypot(det.x_px[:, None] - mirrored.truth_x_px, det.y_px[:, None] - mirrored.truth_y_px)
    single = ~det.blended  # a blend (here a pair 2.9 px apart cut by the border) is flagged, its bias in sigma_px
    assert np.all(d.min(axis=1)[single] < 0.5)  # every other detection sits on a mirrored true star
    # a blend's shift is at most sqrt(2) x its sigma_px (its bias bound), and its noise adds: within 4 of them
    assert np.all(d.min(axis=1)[~single] <= 4.0 * det.sigma_px[~single])


def test_a_noisy_simulation_is_refused():
    noisy = simulate(SimConfig(camera=seed004_camera(), frames=1, noise_px=0.05, min_stars=5))
    with pytest.raises(ValueError, match="noiseless simulation"):
        render_frame(noisy, 0)


def test_whole_chain_finds_every_isolated_unsaturated_star_and_no_hot_pixel(sim):
    config = RenderConfig()  # 20 hot pixels
    frame = render_frame(sim, 0, config)
    det = centroid_pixels(frame.image_adu, CentroidOptions(gain_e_per_adu=2.0), saturation_adu=config.saturation_adu)
    tx, ty = frame.truth_x_px, frame.truth_y_px
    sep_px = np.hypot(tx[:, None] - tx, ty[:, None] - ty) + np.eye(tx.size) * 1e9
    inside = (tx > 8) & (tx < 1015) & (ty > 8) & (ty < 1015)
    hot_near = np.hypot(*(frame.hot_pixels_xy[:, None, :] - np.c_[tx, ty][None]).transpose(2, 0, 1)).min(axis=0)
    clean = inside & (sep_px.min(axis=1) > 10) & ~frame.saturated & (hot_near > 6)
    d = np.hypot(det.x_px[:, None] - tx, det.y_px[:, None] - ty)
    found = np.zeros(tx.size, bool)
    found[d.argmin(axis=1)[d.min(axis=1) < 0.5]] = True
    assert clean.sum() >= 20
    assert np.all(found[clean])  # Hp <= 7 at 2e6 e- for Hp 0: >= 3200 e-, peak SNR >= 30
    single = ~det.blended  # and nothing else: hot pixels rejected, no false star, a blend flagged with its bias
    assert np.all(d.min(axis=1)[single] < 0.5)
    # a blend's shift is at most sqrt(2) x its sigma_px (its bias bound), and its noise adds: within 4 of them
    assert np.all(d.min(axis=1)[~single] <= 4.0 * det.sigma_px[~single])


def test_field_effects_conserve_flux_and_move_a_comatic_star_outward():
    """The field effects (:class:`hostlink.sky.render.FieldEffects`): without vignetting every star's light is all on
    the detector (the sub-pixel sampled elliptical PSF integrates to its flux, to 1 %: 4 x 4 samples per pixel of a
    sigma >= 1.3 px Gaussian); a comatic star's light centroid lies outward from its chief ray by the comatic
    fraction times its displacement (the second component's centre), and the PSF widens toward the corner."""
    from hostlink.sky.render import FieldEffects

    size = (201, 201)
    centre = 100.0
    effects = FieldEffects(psf_corner_factor=2.0, coma_fraction=0.3, coma_corner_px=4.0)
    config = RenderConfig(psf_sigma_px=1.3, background_e=0.0, effects=effects)
    x, y = np.array([100.0, 160.0]), np.array([100.0, 160.0])  # the centre, and along the diagonal at rho^2 = 0.36
    for xs, ys in zip(x, y, strict=True):
        mu = expected_electrons(np.array([xs]), np.array([ys]), np.array([1.0e5]), size, config)
        assert mu.sum() == pytest.approx(1.0e5, rel=0.01)
        rows, cols = np.mgrid[0 : size[1], 0 : size[0]]
        cx, cy = (mu * cols).sum() / mu.sum(), (mu * rows).sum() / mu.sum()
        rho2 = ((xs - centre) ** 2 + (ys - centre) ** 2) / (2 * centre**2)
        shift = effects.coma_fraction * effects.coma_corner_px * rho2 / np.sqrt(2.0)  # per axis, along the diagonal
        assert cx - xs == pytest.approx(shift, abs=0.01)
        assert cy - ys == pytest.approx(shift, abs=0.01)


def test_bayer_jpeg_rgb_keeps_the_channel_responses_of_a_flat_field():
    """A flat field through the Bayer mosaic and its bilinear interpolation: each channel the signal times its
    response (0.9, 1.0, 0.75), scaled so that ``white_adu`` above the bias is 255."""
    from hostlink.sky.render import bayer_jpeg_rgb

    config = RenderConfig()
    image = np.full((16, 20), config.bias_adu + 400.0)
    rgb = bayer_jpeg_rgb(image, config, white_adu=1020.0)
    assert rgb.shape == (16, 20, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[..., 0], 90)  # 0.9 x 400 x 255 / 1020
    np.testing.assert_array_equal(rgb[..., 1], 100)
    np.testing.assert_array_equal(rgb[..., 2], 75)
