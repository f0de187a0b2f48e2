"""The image renderer for tests (docs/architecture.md ``hostlink/sky``): the stars of a simulated frame
(:func:`hostlink.sky.simulate.simulate`, projected through the true camera by ``onboard.camera.unit_to_pixels``)
drawn as a detector would record them, with the truth, so the image chain (centroiding, identification, calibration)
is scored against it.

Model of one exposure, in electrons [e-] per pixel, then converted to counts [ADU]:

1. expected signal mu_i = B + sum_s N_s P_i(x_s, y_s): a sky + dark level B per pixel, and each star's flux N_s
   spread by a circular Gaussian PSF of standard deviation sigma integrated over the pixel's square,
   P_i = [Phi((x_i + 1/2 - x_s) / sigma) - Phi((x_i - 1/2 - x_s) / sigma)] x [same in y]
   (pixel (x_i, y_i) is the pixel centre, docs/camera-model.md); N_s = zero_point_e x 10^(-0.4 mag);
2. shot noise: Poisson(mu_i); hot pixels: a few random pixels get ``hot_pixel_e`` more (dark-current spikes: a
   single pixel, no PSF);
3. read noise: + Normal(0, read_noise_e); counts = round(bias + e / gain), clipped to [0, 2^bits - 1] (the
   ADC's full scale: saturation).

Optional field effects of a real wide lens (:class:`FieldEffects`, all off by default, the model above unchanged
then): a PSF that widens toward the corners and is elongated radially there (coma-like: an extra component of the
star's light displaced outward), vignetting (the light, stars and sky alike, falls off as the square of the radius),
and a sky gradient (light pollution toward one edge). :func:`bayer_jpeg_rgb` turns a rendered frame into what a
colour camera's JPEG holds (a Bayer mosaic, interpolated, scaled to 8 bits).

Everything is drawn from one ``numpy.random.Generator`` seeded by ``RenderConfig.seed`` (and the frame), so a render
is deterministic. :func:`pixel_integrated_gaussian` is the one PSF formula: the Cramer-Rao bound of the centroiders
(:func:`hostlink.images.centroid.centroid_crb_px`) differentiates the same model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import ndtr

if TYPE_CHECKING:  # the simulator (catalogue, ERFA) is not needed to render given positions
    from hostlink.sky.simulate import SimResult

_SQRT_2PI = float(np.sqrt(2.0 * np.pi))
#: Half-width of a star's drawn box in PSF sigmas: the Gaussian beyond 6 sigma holds < 1e-8 of the flux.
_BOX_SIGMAS = 6.0


@dataclass(frozen=True)
class FieldEffects:
    """A real wide lens's departures from the uniform Gaussian PSF, each off at its default. ``psf_corner_factor``:
    the PSF sigma at the detector's corner over the centre's (growing as the square of the radius); ``coma_fraction``
    of each star's light drawn as a second Gaussian displaced outward by ``coma_corner_px`` x (r / R)^2 (R the
    half-diagonal) and elongated radially (a comatic star); ``vignetting_corner``: the fraction of the light lost at
    the corner (1 - v (r / R)^2, stars and sky); ``gradient_e``: sky electrons added linearly from 0 at the top row to
    this at the bottom (light pollution toward a horizon below the frame)."""

    psf_corner_factor: float = 1.0
    coma_fraction: float = 0.0
    coma_corner_px: float = 0.0
    vignetting_corner: float = 0.0
    gradient_e: float = 0.0

    @property
    def active(self) -> bool:
        return self != FieldEffects()


@dataclass(frozen=True)
class RenderConfig:
    """The detector and optics of a render. Units: PSF sigma [px]; electrons [e-]; gain [e-/ADU]; bias [ADU];
    ``zero_point_e`` = electrons of a magnitude-0 star in one exposure."""

    psf_sigma_px: float = 1.2
    zero_point_e: float = 2.0e6
    background_e: float = 40.0
    read_noise_e: float = 8.0
    gain_e_per_adu: float = 2.0
    bias_adu: float = 50.0
    bits: int = 12
    hot_pixels: int = 20
    hot_pixel_e: float = 4000.0
    seed: int = 0
    effects: FieldEffects = field(default_factory=FieldEffects)

    @property
    def saturation_adu(self) -> float:
        """The ADC's full scale [ADU]: a pixel at this value is clipped."""
        return float(2**self.bits - 1)


@dataclass
class RenderedFrame:
    """A rendered image and its truth. ``image_adu`` (height, width) uint16 counts; per truth star: the true centroid
    ``truth_x_px, truth_y_px`` (the PSF centre: camera convention), flux [e-], Hipparcos number (0 for stars not from
    a catalogue), magnitude, and ``saturated`` (its brightest pixel is clipped at full scale); ``hot_pixels_xy``
    (n, 2) the columns and rows of the hot pixels."""

    image_adu: np.ndarray
    truth_x_px: np.ndarray
    truth_y_px: np.ndarray
    truth_flux_e: np.ndarray
    truth_star_id: np.ndarray
    truth_mag: np.ndarray
    saturated: np.ndarray
    hot_pixels_xy: np.ndarray
    config: RenderConfig = field(default_factory=RenderConfig)


def pixel_integrated_gaussian(centres_px: np.ndarray, source_px: float | np.ndarray, sigma_px: float) -> np.ndarray:
    """Fraction of a 1-D Gaussian of standard deviation ``sigma_px`` centred at ``source_px`` that falls in the pixels
    centred at ``centres_px`` [px]: Phi((c + 1/2 - s) / sigma) - Phi((c - 1/2 - s) / sigma). The 2-D pixel-integrated
    circular Gaussian is the outer product of the x and y factors (the PSF is separable)."""
    c = np.asarray(centres_px, dtype=np.float64)
    s = np.asarray(source_px, dtype=np.float64)
    return ndtr((c + 0.5 - s) / sigma_px) - ndtr((c - 0.5 - s) / sigma_px)


def pixel_integrated_gaussian_dsource(
    centres_px: np.ndarray, source_px: float | np.ndarray, sigma_px: float
) -> np.ndarray:
    """Derivative of :func:`pixel_integrated_gaussian` with respect to the source position [1/px]:
    -[phi((c + 1/2 - s) / sigma) - phi((c - 1/2 - s) / sigma)] / sigma, phi the standard normal density."""
    c = np.asarray(centres_px, dtype=np.float64)
    s = np.asarray(source_px, dtype=np.float64)
    upper = (c + 0.5 - s) / sigma_px
    lower = (c - 0.5 - s) / sigma_px
    return -(np.exp(-0.5 * upper**2) - np.exp(-0.5 * lower**2)) / (_SQRT_2PI * sigma_px)


def pixel_integrated_gaussian_dwidth(
    centres_px: np.ndarray, source_px: float | np.ndarray, sigma_px: float
) -> np.ndarray:
    """Derivative of :func:`pixel_integrated_gaussian` with respect to the width sigma [1/px]:
    -[phi(u) u - phi(l) l] / sigma with u, l = (c +- 1/2 - s) / sigma, phi the standard normal density."""
    c = np.asarray(centres_px, dtype=np.float64)
    s = np.asarray(source_px, dtype=np.float64)
    upper = (c + 0.5 - s) / sigma_px
    lower = (c - 0.5 - s) / sigma_px
    return -(np.exp(-0.5 * upper**2) * upper - np.exp(-0.5 * lower**2) * lower) / (_SQRT_2PI * sigma_px)


def expected_electrons(
    x_px: np.ndarray, y_px: np.ndarray, flux_e: np.ndarray, image_size_px: tuple[int, int], config: RenderConfig
) -> np.ndarray:
    """The noiseless image [e- per pixel] (step 1 of the module docstring): background plus every star's
    pixel-integrated Gaussian, each drawn in a box of +-6 sigma around it."""
    width, height = image_size_px
    if config.effects.active:
        return _expected_electrons_field(x_px, y_px, flux_e, image_size_px, config)
    mu = np.full((height, width), float(config.background_e))
    half = int(np.ceil(_BOX_SIGMAS * config.psf_sigma_px)) + 1
    for xs, ys, n in zip(np.asarray(x_px, float), np.asarray(y_px, float), np.asarray(flux_e, float), strict=True):
        x0, x1 = max(int(np.floor(xs)) - half, 0), min(int(np.floor(xs)) + half + 2, width)
        y0, y1 = max(int(np.floor(ys)) - half, 0), min(int(np.floor(ys)) + half + 2, height)
        if x0 >= x1 or y0 >= y1:
            continue
        px = pixel_integrated_gaussian(np.arange(x0, x1), xs, config.psf_sigma_px)
        py = pixel_integrated_gaussian(np.arange(y0, y1), ys, config.psf_sigma_px)
        mu[y0:y1, x0:x1] += n * np.outer(py, px)
    return mu


#: Sub-pixel samples per axis of the field-effect PSF (an elliptical Gaussian is not separable into pixel-integrated
#: factors; 4 x 4 samples integrate a sigma >= 1 px Gaussian to < 1 % of its flux per pixel).
_SUBSAMPLES = 4


def _expected_electrons_field(
    x_px: np.ndarray, y_px: np.ndarray, flux_e: np.ndarray, image_size_px: tuple[int, int], config: RenderConfig
) -> np.ndarray:
    """:func:`expected_electrons` with :class:`FieldEffects`: each star a main Gaussian of the sigma of its radius
    plus its comatic component, radially elongated, integrated over each pixel by sub-pixel sampling; then
    vignetting of stars and sky, then the gradient."""
    fx = config.effects
    width, height = image_size_px
    cx, cy = 0.5 * (width - 1), 0.5 * (height - 1)
    r_corner2 = cx * cx + cy * cy
    mu = np.full((height, width), float(config.background_e))
    sub = (np.arange(_SUBSAMPLES) + 0.5) / _SUBSAMPLES - 0.5
    for xs, ys, n in zip(np.asarray(x_px, float), np.asarray(y_px, float), np.asarray(flux_e, float), strict=True):
        rho2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / r_corner2
        sigma = config.psf_sigma_px * (1.0 + (fx.psf_corner_factor - 1.0) * rho2)
        radius = math.hypot(xs - cx, ys - cy)
        ux, uy = ((xs - cx) / radius, (ys - cy) / radius) if radius > 0 else (1.0, 0.0)
        shift = fx.coma_corner_px * rho2
        components = [(1.0 - fx.coma_fraction, xs, ys, sigma, sigma)]
        if fx.coma_fraction > 0:
            components.append((fx.coma_fraction, xs + shift * ux, ys + shift * uy, sigma + shift, sigma))
        half = int(np.ceil(_BOX_SIGMAS * (sigma + shift))) + 1
        x0, x1 = max(int(np.floor(xs)) - half, 0), min(int(np.floor(xs)) + half + 2, width)
        y0, y1 = max(int(np.floor(ys)) - half, 0), min(int(np.floor(ys)) + half + 2, height)
        if x0 >= x1 or y0 >= y1:
            continue
        gx = (np.arange(x0, x1)[None, :, None, None] + sub[None, None, None, :]).repeat(y1 - y0, 0)
        gy = (np.arange(y0, y1)[:, None, None, None] + sub[None, None, :, None]).repeat(x1 - x0, 1)
        box = np.zeros((y1 - y0, x1 - x0))
        for weight, px, py, s_radial, s_tangential in components:
            dr = (gx - px) * ux + (gy - py) * uy
            dt = -(gx - px) * uy + (gy - py) * ux
            density = np.exp(-0.5 * ((dr / s_radial) ** 2 + (dt / s_tangential) ** 2))
            box += weight * density.mean(axis=(2, 3)) / (2.0 * math.pi * s_radial * s_tangential)
        mu[y0:y1, x0:x1] += n * box
    if fx.vignetting_corner:
        yy, xx = np.mgrid[0:height, 0:width]
        mu *= 1.0 - fx.vignetting_corner * ((xx - cx) ** 2 + (yy - cy) ** 2) / r_corner2
    if fx.gradient_e:
        mu += fx.gradient_e * (np.arange(height, dtype=np.float64) / max(height - 1, 1))[:, None]
    return mu


def bayer_jpeg_rgb(image_adu: np.ndarray, config: RenderConfig, white_adu: float | None = None) -> np.ndarray:
    """What a colour camera's 8-bit file holds of a rendered frame: each pixel sees one colour of an RGGB Bayer
    mosaic (the channels' responses 0.9, 1.0, 0.75 of a white star), the missing colours are interpolated bilinearly
    from the neighbours (the camera's demosaicing), the bias removed and the counts scaled so that ``white_adu``
    (default: full scale less the bias) is 255. Returns (height, width, 3) uint8; write it as JPEG to add the
    compression."""
    from scipy.ndimage import convolve

    height, width = image_adu.shape
    signal = np.asarray(image_adu, dtype=np.float64) - config.bias_adu
    white = (config.saturation_adu - config.bias_adu) if white_adu is None else white_adu
    yy, xx = np.mgrid[0:height, 0:width]
    masks = (((yy % 2) == 0) & ((xx % 2) == 0), ((yy + xx) % 2) == 1, ((yy % 2) == 1) & ((xx % 2) == 1))
    kernel = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]])
    channels = []
    for mask, response in zip(masks, (0.9, 1.0, 0.75), strict=True):
        sampled = np.where(mask, signal * response, 0.0)
        weight = convolve(mask.astype(np.float64), kernel, mode="mirror")
        channels.append(convolve(sampled, kernel, mode="mirror") / weight)
    rgb = np.stack(channels, axis=-1) * (255.0 / white)
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)


def render_stars(
    x_px: np.ndarray,
    y_px: np.ndarray,
    flux_e: np.ndarray,
    image_size_px: tuple[int, int],
    config: RenderConfig = RenderConfig(),
    seed: int | None = None,
    star_id: np.ndarray | None = None,
    mag: np.ndarray | None = None,
) -> RenderedFrame:
    """Render stars at true centroids ``(x_px, y_px)`` [px] with fluxes ``flux_e`` [e-] on a detector of
    ``image_size_px = (width, height)`` (the module docstring's model); ``seed`` overrides ``config.seed``."""
    x = np.asarray(x_px, dtype=np.float64)
    y = np.asarray(y_px, dtype=np.float64)
    flux = np.asarray(flux_e, dtype=np.float64)
    width, height = image_size_px
    rng = np.random.default_rng(config.seed if seed is None else seed)
    mu = expected_electrons(x, y, flux, image_size_px, config)
    electrons = rng.poisson(mu).astype(np.float64)
    hot = np.stack([rng.integers(0, width, config.hot_pixels), rng.integers(0, height, config.hot_pixels)], axis=1)
    electrons[hot[:, 1], hot[:, 0]] += config.hot_pixel_e
    electrons += rng.normal(0.0, config.read_noise_e, electrons.shape)
    counts = np.clip(np.round(config.bias_adu + electrons / config.gain_e_per_adu), 0, config.saturation_adu)
    # a star is saturated when its brightest expected pixel reaches full scale
    peak_e = np.array([_peak_expected(mu, xs, ys) for xs, ys in zip(x, y, strict=True)])
    saturated = config.bias_adu + peak_e / config.gain_e_per_adu >= config.saturation_adu
    return RenderedFrame(
        image_adu=counts.astype(np.uint16),
        truth_x_px=x,
        truth_y_px=y,
        truth_flux_e=flux,
        truth_star_id=np.zeros(x.size, np.int64) if star_id is None else np.asarray(star_id, np.int64),
        truth_mag=np.full(x.size, np.nan) if mag is None else np.asarray(mag, np.float64),
        saturated=saturated,
        hot_pixels_xy=hot,
        config=config,
    )


def _peak_expected(mu: np.ndarray, x: float, y: float) -> float:
    h, w = mu.shape
    c, r = int(round(x)), int(round(y))
    if not (0 <= c < w and 0 <= r < h):
        return 0.0
    return float(mu[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2].max())


def render_frame(
    sim: SimResult, frame: int, config: RenderConfig = RenderConfig(), mirrored: bool = False
) -> RenderedFrame:
    """Render frame ``frame`` of a simulation. The simulation must be noiseless (``SimConfig.noise_px = 0``): its
    centroids are then exactly the true camera's projection of each star (``onboard.camera.unit_to_pixels`` of the
    attitude times the star's direction) and are the truth here; the rendered noise is the image's own. Give the
    ``SimConfig`` a ``max_stars`` large enough to hold every star the detector sees and a ``maglim`` near the
    detection limit. False stars of the simulation (``star_id`` 0) are not drawn. ``mirrored``: a mirrored detector
    (columns reversed, x -> width - 1 - x, in image and truth). The render's seed is ``config.seed`` + ``frame``."""
    if float(sim.truth.get("noise_px", 0.0)) != 0.0:
        raise ValueError(
            "render_frame needs a noiseless simulation (SimConfig.noise_px = 0): its centroids are the truth"
        )
    session = sim.session
    rows = np.flatnonzero((session.frame == frame) & (session.star_id != 0))
    width, height = (int(v) for v in sim.truth["camera"]["image_size_px"])
    x = session.x_px[rows].copy()
    if mirrored:
        x = (width - 1) - x
    mag = session.mag[rows] if session.mag is not None else np.full(rows.size, np.nan)
    flux = config.zero_point_e * 10.0 ** (-0.4 * mag)
    return render_stars(
        x,
        session.y_px[rows],
        flux,
        (width, height),
        config,
        seed=config.seed + int(frame),
        star_id=session.star_id[rows],
        mag=mag,
    )
