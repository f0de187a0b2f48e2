"""``hostlink calibrate`` says what a nominal focal length far from the stars' points to: a factor near 2 to a binning
left out of the pixel pitch, a larger factor to a nominal of another camera (it said "a factor near 2" for every
factor beyond 1.65, e.g. 5 x for another camera's nominal file)."""

import json

import pytest

from hostlink.api import focal_hint
from hostlink.cli import main

BINNING = "a factor near 2: check the pixel pitch for binning"
OTHER_CAMERA = "check that the nominal is this camera's"


@pytest.mark.parametrize(
    ("ratio", "expected"),
    [
        (0.5, BINNING),
        (2.0, BINNING),
        (1 / 1.9, BINNING),  # binned, and the lens 5 % off its nominal
        (2.4, BINNING),
        (0.2, OTHER_CAMERA),  # granasat's stars against openstartracker's nominal (docs/realsky.md)
        (5.0, OTHER_CAMERA),
        (1 / 18.8, OTHER_CAMERA),  # a fisheye nominal
        (1.3, ""),
        (0.9, ""),
    ],
)
def test_the_hint_follows_the_factor(ratio, expected):
    hint = focal_hint(ratio)
    assert (expected in hint) if expected else hint == "", hint


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    work = tmp_path_factory.mktemp("hint")
    path = work / "s.csv"
    assert main(["simulate", "--preset", "seed004", "--frames", "30", "--out", str(path)]) == 0
    return path


@pytest.mark.parametrize(
    ("nominal", "expected", "absent"),
    [
        # the seed004 camera's nominal with five times its focal length: another camera's file
        ({"focal_length_mm": 350.0, "pixel_pitch_um": 12.0}, OTHER_CAMERA, BINNING),
        # its pitch given for 2 x 2 binned pixels while the session is unbinned: half the focal length in pixels
        ({"focal_length_mm": 70.0, "pixel_pitch_um": 24.0}, BINNING, OTHER_CAMERA),
    ],
)
def test_calibrate_prints_the_hint(session, tmp_path, capsys, nominal, expected, absent):
    path = tmp_path / "nominal.json"
    path.write_text(json.dumps(nominal | {"principal_point_px": [511.5, 511.5], "image_size_px": [1024, 1024]}))
    capsys.readouterr()
    code = main(["calibrate", str(session), "--nominal", str(path), "--out", str(tmp_path / "cal.json")])
    out = " ".join(capsys.readouterr().out.split())  # the report wraps its lines
    assert code == 0 and "focal length from the stars" in out and expected in out and absent not in out, out
