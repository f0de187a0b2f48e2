"""scripts/newcamera.py's image forms (docs/realsky.md, "A new camera: what was tried") are what they claim: each
written file reads back as the original's pixels moved or scaled as stated, and a star's centroid in the written
form, mapped back by the form's own map, is the original's (the comparison of names between forms rests on it)."""

import numpy as np
import pytest
from PIL import Image
from scripts_loader import load_script

from hostlink.images.centroid import CentroidOptions, centroid_pixels
from hostlink.images.read import read_image
from hostlink.sky.render import RenderConfig, render_stars

#: a multiple of SEP's 64 px background mesh: flipped or rotated, its boxes cover the same pixels
SIZE = (256, 192)


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    """A rendered 8-bit colour PNG (the channels differ, as openstartracker's do) with 12 stars, and their places."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(15, SIZE[0] - 15, 12), rng.uniform(15, SIZE[1] - 15, 12)
    grey = render_stars(x, y, np.full(12, 40000.0), SIZE, RenderConfig(bits=8, gain_e_per_adu=40.0)).image_adu
    rgb = np.stack([grey, np.clip(grey.astype(int) + 1, 0, 255), grey], axis=2).astype(np.uint8)
    path = tmp_path_factory.mktemp("forms") / "frame.png"
    Image.fromarray(rgb).save(path)
    return path, x, y


@pytest.mark.parametrize("form", ["fits16", "tiff16", "rgb", "flip", "rot180", "rot90", "bin2"])
def test_each_form_maps_back_to_the_original(original, form, tmp_path):
    script = load_script("newcamera.py")
    path, true_x, true_y = original
    (written,) = script.write_form([path], form, tmp_path)
    grey, out = read_image(path).pixels, read_image(written)
    expected = {
        "fits16": grey * script.SCALE_16,
        "tiff16": grey * script.SCALE_16,
        "rgb": grey,
        "flip": grey[:, ::-1],
        "rot180": grey[::-1, ::-1],
        "rot90": np.rot90(grey),
        "bin2": grey.reshape(96, 2, 128, 2).sum(axis=(1, 3)) * script.SCALE_BIN,
    }[form]
    np.testing.assert_allclose(out.pixels, expected, rtol=0, atol=0.5)  # the stated rounding to integers
    if form == "bin2":
        assert out.saturation_adu == 4 * 255 * script.SCALE_BIN
    options = CentroidOptions(candidate_sigma=None)
    base = centroid_pixels(grey, options, None, 255.0)
    det = centroid_pixels(out.pixels, options, None, out.saturation_adu)
    x, y = script.form_writer(form)[2](det.x_px, det.y_px, *out.image_size_px)  # the form's own size
    # the original's centroids of the rendered stars: each within 0.1 px of its star (0.052 px at most here, the 8-bit
    # rounding of a nearly noiseless frame); its other detections are not stars (one 5.8 px off the star at
    # (131.8, 65.9), kept flagged as a blend with a sigma_px of 0.67 px, is not in the binned frame, nor should be)
    to_star = np.hypot(base.x_px[:, None] - true_x[None], base.y_px[:, None] - true_y[None])
    assert np.all(to_star.min(axis=0) < 0.1), to_star.min(axis=0)
    stars = to_star.argmin(axis=0)
    d = np.hypot(x[:, None] - base.x_px[stars][None], y[:, None] - base.y_px[stars][None]).min(axis=0)
    # every star of the original at its place: the lossless forms to 1e-5 px (the same pixels in another order; the
    # 16-bit rounding, 0.5 / 257 ADU, moved them by < 1e-7 px here), bin2 to 0.3 original px (4 x the binned stars'
    # median sigma_px of 0.039 binned px; they moved by up to 0.066 px here)
    assert np.all(d < (0.3 if form == "bin2" else 1e-5)), d
