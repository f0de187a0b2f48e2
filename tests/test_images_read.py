"""THE image reader (hostlink.images.read): every format into one float64 array in the camera convention, with the
exposure time from the file's metadata, and a one-line error for what it cannot read."""

from __future__ import annotations

import numpy as np
import pytest

from hostlink.errors import UserError
from hostlink.images.read import read_image


def _ramp(dtype, height: int = 12, width: int = 16) -> np.ndarray:
    """A test pattern whose value names its pixel: 100 * row + column (row 0 first)."""
    rows, cols = np.mgrid[0:height, 0:width]
    return (100 * rows + cols).astype(dtype)


def test_fits_keeps_row_and_column_order_and_scales_unsigned_16_bit(tmp_path):
    from astropy.io import fits

    data = _ramp(np.uint16) + 60000  # above 32767: stored as int16 with BZERO 32768
    path = tmp_path / "a.fits"
    fits.PrimaryHDU(data).writeto(path)
    image = read_image(path)
    np.testing.assert_array_equal(image.pixels, data.astype(np.float64))  # exact: integers below 2^53
    assert image.pixels[3, 5] == 60000 + 305  # pixels[row, column]: x = 5, y = 3 (camera convention)
    assert image.saturation_adu == 65535.0  # BZERO 32768 + 32767
    assert image.time_utc is None


def test_fits_time_is_mid_exposure_from_date_obs_plus_half_exptime(tmp_path):
    from astropy.io import fits

    hdu = fits.PrimaryHDU(_ramp(np.int16))
    hdu.header["DATE-OBS"] = "2018-05-09T03:00:00.000"
    hdu.header["EXPTIME"] = 0.05
    path = tmp_path / "t.fits"
    hdu.writeto(path)
    image = read_image(path)
    assert image.time_utc == "2018-05-09T03:00:00.025Z"
    assert "EXPTIME" in image.time_source


def test_fits_time_in_tt_is_converted_to_utc(tmp_path):
    from astropy.io import fits

    hdu = fits.PrimaryHDU(_ramp(np.int16))
    hdu.header["DATE-AVG"] = "2018-05-09T03:01:09.184"
    hdu.header["TIMESYS"] = "TT"
    path = tmp_path / "tt.fits"
    hdu.writeto(path)
    # TT - UTC = 32.184 s + 37 leap seconds in 2018 (IERS Bulletin C): 69.184 s
    assert read_image(path).time_utc == "2018-05-09T03:00:00.000Z"


def test_fits_time_in_gps_is_tai_minus_19_s(tmp_path):
    from astropy.io import fits

    hdu = fits.PrimaryHDU(_ramp(np.int16))
    hdu.header["DATE-AVG"] = "2018-05-09T03:00:18.000"
    hdu.header["TIMESYS"] = "GPS"
    path = tmp_path / "gps.fits"
    hdu.writeto(path)
    # GPS - UTC = (TAI - 19 s) - UTC = 37 - 19 = 18 s in 2018 (IERS Bulletin C)
    assert read_image(path).time_utc == "2018-05-09T03:00:00.000Z"


@pytest.mark.parametrize("dtype, full_scale", [(np.uint8, 255.0), (np.uint16, 65535.0)])
def test_tiff_8_and_16_bit_read_exactly_with_their_full_scale(tmp_path, dtype, full_scale):
    import tifffile

    data = _ramp(dtype) % int(full_scale)
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, data)
    image = read_image(path)
    np.testing.assert_array_equal(image.pixels, data.astype(np.float64))
    assert image.saturation_adu == full_scale
    assert image.image_size_px == (16, 12)


def test_png_16_bit_and_colour_as_mean_of_channels(tmp_path):
    from PIL import Image

    grey = _ramp(np.uint16) * 50
    Image.fromarray(grey).save(tmp_path / "g.png")
    image = read_image(tmp_path / "g.png")
    np.testing.assert_array_equal(image.pixels, grey.astype(np.float64))
    assert image.saturation_adu == 65535.0

    rgba = np.zeros((12, 16, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = 30, 60, 90, 255
    Image.fromarray(rgba, "RGBA").save(tmp_path / "c.png")
    colour = read_image(tmp_path / "c.png")
    np.testing.assert_array_equal(colour.pixels, np.full((12, 16), 60.0))  # (30 + 60 + 90) / 3; alpha ignored
    assert colour.saturation_adu == 255.0


def test_png_exif_time_shifted_to_utc_and_to_mid_exposure(tmp_path):
    from PIL import Image

    im = Image.fromarray(_ramp(np.uint8))
    exif = Image.Exif()
    exif_ifd = {0x9003: "2018:05:09 05:00:00", 0x9011: "+02:00", 0x9291: "5", 0x829A: 0.1}
    exif[0x8769] = exif_ifd
    path = tmp_path / "e.png"
    im.save(path, exif=exif)
    image = read_image(path)
    # 05:00:00.5 at UTC+2 = 03:00:00.5 UTC, + 0.1 s / 2
    assert image.time_utc == "2018-05-09T03:00:00.550Z"
    assert image.time_source.startswith("EXIF DateTimeOriginal")


def test_truncated_png_is_one_line_error_naming_the_file(tmp_path):
    from PIL import Image

    path = tmp_path / "full.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (200, 200), dtype=np.uint8)).save(path)
    cut = tmp_path / "cut.png"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(UserError, match=r"cut\.png: cannot read the image \(") as info:
        read_image(cut)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "name, message",
    [("x.jpg2", "unknown image type"), ("missing.png", "no such file")],
)
def test_unknown_suffix_and_missing_file_are_one_line_errors(tmp_path, name, message):
    with pytest.raises(UserError, match=message):
        read_image(tmp_path / name)


def test_a_cube_is_refused(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "cube.tif", np.zeros((5, 12, 16), np.uint16))
    with pytest.raises(UserError, match="not a single image"):
        read_image(tmp_path / "cube.tif")
