"""``hostlink centroid``: rendered images in three formats -> one session of unidentified stars, with the time of
each image from an option, a list, the file name or the file's metadata, and one-line errors for what is missing."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hostlink.cli import main
from hostlink.files.session import read_session
from hostlink.images.guided import candidate_rows
from hostlink.sky.render import RenderConfig, render_stars

SIZE = (200, 160)
#: Fixed-pattern warm clusters (column, row of their top-left pixel) for the median-frame test.
WARM = ((100, 8), (7, 150), (190, 100))


def _stars(seed: int):
    """Nine well-separated stars of 3000 to 20000 e- on a grid shifted by the seed (another pointing), with 6 hot
    pixels."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(3), np.arange(3))
    shift_x, shift_y = rng.uniform(0, 40, 2)
    x = 20.0 + shift_x + 60.0 * gx.ravel() + rng.uniform(-0.5, 0.5, 9)
    y = 15.0 + shift_y + 50.0 * gy.ravel() + rng.uniform(-0.5, 0.5, 9)
    flux = np.geomspace(20000.0, 3000.0, 9)
    return render_stars(x, y, flux, SIZE, RenderConfig(hot_pixels=6), seed=seed)


def _clean(frame) -> np.ndarray:
    """Stars with no hot pixel within 6 px (a hot pixel on a star's wing makes it a blend, rightly rejected)."""
    hot = frame.hot_pixels_xy.astype(float)
    d = np.hypot(hot[:, None, 0] - frame.truth_x_px, hot[:, None, 1] - frame.truth_y_px)
    return d.min(axis=0) > 6


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """The same kind of field as FITS (with DATE-OBS), 16-bit TIFF and PNG files, named with their time."""
    import tifffile
    from astropy.io import fits
    from PIL import Image

    folder = tmp_path_factory.mktemp("images")
    frames = [_stars(seed) for seed in range(3)]
    hdu = fits.PrimaryHDU(frames[0].image_adu)
    hdu.header["DATE-OBS"] = "2018-05-09T03:10:00.000"
    hdu.header["EXPTIME"] = 2.0
    paths = [
        folder / "sky_20180509_031000.fits",
        folder / "sky_20180509_030000.tif",
        folder / "sky_20180509_032000.png",
    ]
    hdu.writeto(paths[0])
    tifffile.imwrite(paths[1], frames[1].image_adu)
    Image.fromarray(frames[2].image_adu).save(paths[2])
    return paths, frames


def test_three_formats_become_one_session_in_time_order(images, tmp_path, capsys):
    paths, frames = images
    out = tmp_path / "s.csv"
    pattern = "sky_%Y%m%d_%H%M%S"
    assert main(["centroid", *map(str, paths), "--time-pattern", pattern, "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    per_image = re.compile(
        r"^frame \d \S+: (\d+) stars of (\d+) detections \(rejected: (\d+) hot, (\d+) saturated, (\d+) blended, "
        r"(\d+) at the edge, (\d+) without flux; \d+ saturated kept, \d+ blends kept flagged\); "
        r"noise [\d.]+ ADU, PSF sigma [\d.]+ px; "
        r"time 2018-05-09T03:[012]0:00.000Z"
    )
    counts = [tuple(int(v) for v in per_image.match(line).groups()) for line in printed[:3]]
    assert all(kept + sum(rejected) == detected for kept, detected, *rejected in counts)  # every detection accounted
    assert sum(hot for _, _, hot, *_ in counts) >= 12  # 18 hot pixels rendered; a few fall on a star's wing
    assert printed[3].endswith(f"stars in 3 images; wrote {out}")
    session = read_session(out)
    assert session.n_frames == 3
    # time order: the TIFF (03:00), the FITS (03:10), the PNG (03:20)
    assert list(session.extra["image"][session.frame_starts[:-1]]) == [paths[1].name, paths[0].name, paths[2].name]
    assert list(session.t_utc[session.frame_starts[:-1]]) == [
        "2018-05-09T03:00:00.000Z",
        "2018-05-09T03:10:00.000Z",
        "2018-05-09T03:20:00.000Z",
    ]
    assert np.all(session.star_id == 0)
    for k, truth in zip(range(3), [frames[1], frames[0], frames[2]], strict=True):
        rows = (session.frame == k) & ~candidate_rows(session)  # the detected stars (not the faint candidates)
        d = np.hypot(session.x_px[rows][:, None] - truth.truth_x_px, session.y_px[rows][:, None] - truth.truth_y_px)
        assert np.all(d.min(axis=1) < 0.1)  # only stars (no hot pixel); flux >= 3000 e-: CRB <= 0.04 px, 2.5 x
        found = np.zeros(9, bool)
        found[d.argmin(axis=1)] = True
        assert np.all(found[_clean(truth)])  # every star clear of hot pixels
        mag = session.mag[rows]
        assert np.all(np.diff(mag) >= 0)  # brightest first
        flux = np.array(session.extra["flux_adu"][rows], dtype=float)
        np.testing.assert_allclose(mag, -2.5 * np.log10(flux), atol=2e-3)  # mag to 3 decimals, flux to 0.1 ADU


def test_fits_metadata_time_is_used_when_no_option_is_given(images, tmp_path):
    paths, _ = images
    out = tmp_path / "f.csv"
    assert main(["centroid", str(paths[0]), "--out", str(out), "--quiet"]) == 0
    session = read_session(out)
    assert set(session.t_utc) == {"2018-05-09T03:10:01.000Z"}  # DATE-OBS + EXPTIME / 2
    assert set(session.extra["time_source"]) == {"FITS DATE-OBS + EXPTIME/2"}


def test_times_file_date_and_unknown_time(images, tmp_path):
    paths, _ = images
    listing = tmp_path / "times.txt"
    listing.write_text(f"# name, time\n{paths[1].name},2018-05-09T01:00:00Z\n{paths[2].name} 2018-05-09T01:00:01Z\n")
    out = tmp_path / "t.csv"
    assert main(["centroid", str(paths[1]), str(paths[2]), "--times", str(listing), "--out", str(out), "--quiet"]) == 0
    assert list(read_session(out).t_utc[[0, -1]]) == ["2018-05-09T01:00:00Z", "2018-05-09T01:00:01Z"]

    assert main(["centroid", str(paths[1]), "--date", "2018-05-09", "--out", str(out), "--quiet"]) == 0
    assert set(read_session(out).t_utc) == {"2018-05-09T12:00:00.000Z"}

    assert main(["centroid", str(paths[1]), str(paths[2]), "--time-unknown", "--out", str(out), "--quiet"]) == 0
    unknown = read_session(out)
    assert not unknown.time_known and unknown.n_frames == 2  # the session format's "time unknown"


def test_each_frame_line_says_its_time_and_source_or_once_that_it_has_none(images, tmp_path, capsys):
    paths, _ = images
    out = tmp_path / "u.csv"
    assert main(["centroid", str(paths[0]), "--out", str(out)]) == 0
    assert "time 2018-05-09T03:10:01.000Z (FITS DATE-OBS + EXPTIME/2);" in capsys.readouterr().out
    assert main(["centroid", str(paths[0]), "--time-unknown", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "; time unknown; " in printed and "(unknown)" not in printed


@pytest.mark.parametrize(
    "extra, needle",
    [
        ([], "sky_20180509_030000.tif: no time known"),
        (["--time-pattern", "img_%H%M"], "sky_20180509_030000.tif: the file name does not match --time-pattern"),
        (["--time", "yesterday"], "--time: not an ISO 8601 UTC time"),
        (["--date", "2018-13-01"], "--date: not a date YYYY-MM-DD"),
        (["--time-unknown", "--threshold-sigma", "0"], "threshold-sigma must be a number > 0"),
        (["--time-unknown", "--dark", "missing.fits"], "missing.fits: no such file"),
    ],
)
def test_time_and_option_errors_are_one_line_naming_the_image(images, tmp_path, capsys, extra, needle):
    paths, _ = images
    out = tmp_path / "e.csv"
    code = main(["centroid", str(paths[1]), *extra, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert needle in err and "\n" not in err
    assert not out.exists()


def test_image_missing_from_the_times_file_is_named(images, tmp_path, capsys):
    paths, _ = images
    listing = tmp_path / "times.txt"
    listing.write_text(f"{paths[1].name},2018-05-09T01:00:00Z\n")
    code = main(["centroid", str(paths[1]), str(paths[2]), "--times", str(listing), "--out", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and f"{paths[2].name}: not listed in the times file" in err


def test_no_star_in_any_image_fails_without_writing(tmp_path, capsys):
    import tifffile

    blank = tmp_path / "blank.tif"
    tifffile.imwrite(blank, np.full((100, 120), 200, np.uint16))
    out = tmp_path / "b.csv"
    code = main(["centroid", str(blank), "--time-unknown", "--out", str(out)])
    assert code == 2 and "no star found" in capsys.readouterr().err
    assert not out.exists()


def test_median_of_inputs_removes_a_fixed_pattern(images, tmp_path):
    """The per-pixel median of frames at different pointings keeps the fixed pattern (here, three warm 2 x 2 pixel
    clusters on every frame) and drops the stars: subtracting it leaves only the stars."""
    import tifffile

    paths = []
    for seed in range(3):
        image = _stars(10 + seed).image_adu.astype(np.int64)
        for col, row in WARM:  # warm clusters: not single pixels, so no hot-pixel test can catch them
            image[row : row + 2, col : col + 2] += 400
        path = tmp_path / f"m{seed}.tif"
        tifffile.imwrite(path, np.clip(image, 0, 65535).astype(np.uint16))
        paths.append(str(path))
    plain, median = tmp_path / "plain.csv", tmp_path / "median.csv"
    assert main(["centroid", *paths, "--time-unknown", "--out", str(plain), "--quiet"]) == 0
    assert main(["centroid", *paths, "--time-unknown", "--median-of-inputs", "--out", str(median), "--quiet"]) == 0

    def on_warm(session) -> np.ndarray:
        return np.array(
            [
                [np.hypot(x - c - 0.5, y - r - 0.5) < 1 for c, r in WARM]
                for x, y in zip(session.x_px, session.y_px, strict=True)
            ]
        ).any(axis=1)

    assert on_warm(read_session(plain)).sum() == 3 * len(WARM)  # without the median: seen in every frame
    assert not on_warm(read_session(median)).any()  # with it: gone
    assert len(read_session(median)) >= sum(_clean(_stars(10 + seed)).sum() for seed in range(3))


def test_median_of_inputs_refuses_images_that_share_a_pointing(tmp_path, capsys):
    """Three exposures of the same field (a tracking mount): their median holds the stars, and subtracting it would
    leave nothing but noise. Refused, in one line."""
    import tifffile

    paths = []
    for seed in range(3):
        same_field = _stars(20)  # the same stars every time
        image = render_stars(
            same_field.truth_x_px, same_field.truth_y_px, same_field.truth_flux_e, SIZE, RenderConfig(), seed=30 + seed
        ).image_adu
        tifffile.imwrite(tmp_path / f"s{seed}.tif", image)
        paths.append(str(tmp_path / f"s{seed}.tif"))
    code = main(["centroid", *paths, "--time-unknown", "--median-of-inputs", "--out", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "the images share a pointing" in err and "\n" not in err
