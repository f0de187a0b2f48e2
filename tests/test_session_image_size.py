"""Issue 30: a session records the size of the images its centroids were measured in (``image_width_px``,
``image_height_px``, written by ``hostlink centroid``), keeps it through every rewrite (``identify``), and a nominal of
another detector size is refused in one line (exit 2) by every command that takes one, where before a wrong nominal
whose detector held the centroids (another, larger camera's) was fitted. A session without the columns behaves as
before."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hostlink.cli import main
from hostlink.errors import UserError
from hostlink.files.params import load_params
from hostlink.files.session import (
    IMAGE_SIZE_COLUMNS,
    Session,
    check_on_detector,
    concatenate_sessions,
    image_size_mismatch,
    image_sizes_px,
    read_session,
    write_session,
)
from hostlink.sky.render import RenderConfig, render_stars
from hostlink.sky.simulate import seed004_config, simulate
from onboard.params import params_to_dict

NOMINAL = load_params("builtin:seed004_nominal")  # 1024 x 1024 px
#: Another camera's nominal whose detector holds every centroid of a 1024 x 1024 px session (the gap of issue 30:
#: nothing but the recorded size tells them apart); its principal point at its own centre.
WIDER = replace(NOMINAL, image_size_px=(1280, 1024), principal_point_px=(639.5, 511.5))


def _with_size(session, width: int, height: int):
    n = len(session)
    sizes = {"image_width_px": np.full(n, str(width), object), "image_height_px": np.full(n, str(height), object)}
    return replace(session, extra={**session.extra, **sizes})


#: Seconds an emulated sensor is given to refuse the session: it does so before serving, in about a second; a sensor
#: that accepted it would serve until stopped, and the test then fails instead of waiting for ever.
REFUSAL_WAIT_S = 120


def _hostlink(argv: list[str]) -> subprocess.CompletedProcess:
    code = "import sys; from hostlink.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, check=False, timeout=REFUSAL_WAIT_S
    )


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "internal error" not in err
    return err


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A simulated 1024 x 1024 px session (8 frames, identified), with and without the image size, a blind copy
    (star_id 0, no directions) with it, and the wider nominal."""
    work = tmp_path_factory.mktemp("imgsize")
    session = simulate(seed004_config(frames=8, seed=5)).session
    write_session(work / "old.csv", session)
    write_session(work / "new.csv", _with_size(session, 1024, 1024))
    blind = replace(_with_size(session, 1024, 1024), star_id=np.zeros_like(session.star_id), ra_deg=None, dec_deg=None)
    write_session(work / "blind.csv", blind)
    (work / "wider.json").write_text(json.dumps(params_to_dict(WIDER)))
    return work


def _image(width: int, height: int, seed: int) -> np.ndarray:
    """A rendered frame of 12 stars on a grid (no hot pixels), ``height`` x ``width`` ADU."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(4), np.arange(3))
    x = 20.0 + (width - 40) / 3 * gx.ravel() + rng.uniform(-2, 2, 12)
    y = 20.0 + (height - 40) / 2 * gy.ravel() + rng.uniform(-2, 2, 12)
    return render_stars(
        x, y, np.geomspace(30000, 5000, 12), (width, height), RenderConfig(hot_pixels=0), seed
    ).image_adu


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_centroid_records_each_image_size(tmp_path, suffix):
    from astropy.io import fits

    paths = []
    for k in range(2):
        paths.append(tmp_path / f"f{k}.fits")
        fits.PrimaryHDU(_image(200, 160, k)).writeto(paths[-1])
    out = tmp_path / f"c{suffix}"
    assert main(["centroid", *map(str, paths), "--time-unknown", "--quiet", "--out", str(out)]) == 0
    session = read_session(out)
    assert session.n_frames == 2 and len(session) >= 2 * 10  # the stars were found (12 per frame rendered)
    assert set(session.extra["image_width_px"]) == {"200"} and set(session.extra["image_height_px"]) == {"160"}
    np.testing.assert_array_equal(image_sizes_px(session), np.tile([200, 160], (len(session), 1)))


def test_identify_keeps_the_image_size_and_calibrate_then_refuses_a_wider_nominal(files, tmp_path, capsys):
    out = tmp_path / "ident.csv"
    argv = ["identify", str(files / "blind.csv"), "--nominal", "builtin:seed004_nominal", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    before, after = read_session(files / "blind.csv"), read_session(out)
    assert np.count_nonzero(after.star_id) >= 0.9 * len(after)  # identified (not a rewrite of a failure)
    for name in IMAGE_SIZE_COLUMNS:  # kept, row by row
        np.testing.assert_array_equal(after.extra[name], before.extra[name])
    code = main(["calibrate", str(out), "--nominal", str(files / "wider.json"), "--out", str(tmp_path / "c.json")])
    err = _one_line(capsys)
    assert code == 2 and "images are 1024 x 1024 px" in err and "is 1280 x 1024 px" in err
    assert not (tmp_path / "c.json").exists()


#: Every command that takes a session and a nominal: calibrate chunk by chunk (its default) and read whole
#: (--rejected), identify, replay, attitude, and the emulated sensor replaying the session (which writes nothing).
COMMANDS = {
    "calibrate": ["calibrate", "new.csv", "--out", "OUT", "--nominal"],
    "calibrate --rejected": ["calibrate", "new.csv", "--rejected", "OUT.rejected.csv", "--out", "OUT", "--nominal"],
    "identify": ["identify", "blind.csv", "--out", "OUT", "--nominal"],
    "replay": ["replay", "new.csv", "--out", "OUT", "--nominal"],
    "attitude": ["attitude", "new.csv", "--out", "OUT", "--params"],
    "emulate --replay": ["emulate", "--transport", "serial", "--replay", "new.csv", "--nominal"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_nominal_of_another_detector_size_is_refused_in_one_line(files, tmp_path, capsys, command):
    out = tmp_path / "out"
    argv = [
        a.replace("OUT", str(out)) if "OUT" in a else (str(files / a) if a.endswith(".csv") else a)
        for a in COMMANDS[command]
    ]
    if argv[0] == "emulate":  # its own process: a sensor that accepted the session would serve until stopped
        done = _hostlink([*argv, str(files / "wider.json")])
        code, err = done.returncode, done.stderr
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    else:
        code = main([*argv, str(files / "wider.json")])
        err = _one_line(capsys)
    assert code == 2
    assert "its images are 1024 x 1024 px (frame 0) but the detector of" in err and "is 1280 x 1024 px" in err
    assert "a window (crop) of the detector?" in err  # 1024 x 1024 fits inside 1280 x 1024
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_a_session_without_the_image_size_calibrates_as_before(files, tmp_path):
    """The gap the column closes: the wider nominal is fitted to an old session (exit 0), as before. With the right
    nominal the column changes nothing in the result."""
    wider = ["--nominal", str(files / "wider.json"), "--quiet", "--out"]
    assert main(["calibrate", str(files / "old.csv"), *wider, str(tmp_path / "wider.json")]) == 0
    right = ["--nominal", "builtin:seed004_nominal", "--quiet", "--out"]
    assert main(["calibrate", str(files / "old.csv"), *right, str(tmp_path / "old.json")]) == 0
    assert main(["calibrate", str(files / "new.csv"), *right, str(tmp_path / "new.json")]) == 0
    old, new = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("old", "new"))
    assert new["focal_length_mm"] == old["focal_length_mm"]
    assert new["principal_point_px"] == old["principal_point_px"]
    assert new["residuals"] == old["residuals"]


def test_the_refusal_names_a_turned_binned_or_windowed_image():
    """A 90-deg turned image swaps width and height, k x k binning divides each side (rounding down, as
    scripts/newcamera.py's bin2 form keeps whole pixel pairs); the hint gives the nominal that fits (the principal
    point as newcamera.form_nominal moves it: (x0 - 0.5) / 2 for 2 x 2)."""
    assert "turned 90 deg?" in image_size_mismatch((960, 1280), (1280, 960))
    assert "image_size_px [960, 1280]" in image_size_mismatch((960, 1280), (1280, 960))
    binned = image_size_mismatch((640, 480), (1281, 961))
    assert "binned 2 x 2?" in binned and "pixel_pitch_um x 2" in binned and "(x0 - 0.5) / 2" in binned
    assert "binned 3 x 3?" in image_size_mismatch((426, 320), (1280, 960))
    assert "(y0 - 1) / 3" in image_size_mismatch((426, 320), (1280, 960))
    for other in [(2560, 1920), (1024, 1024), (1300, 900)]:  # larger on a side: not from this detector
        assert image_size_mismatch(other, (1280, 960)) == "; the parameter file does not describe this camera"
    for window in [(1000, 900), (640, 481), (1280, 959)]:  # smaller, neither turned nor binned: a readout window
        hint = image_size_mismatch(window, (1280, 960))
        assert "a window (crop) of the detector?" in hint and f"image_size_px [{window[0]}, {window[1]}]" in hint


def test_binned_images_match_the_binned_nominal_and_not_the_full_one(tmp_path, capsys):
    """scripts/newcamera.py's bin2 form: the sum of 2 x 2 pixels; the nominal it writes for it (half the size,
    twice the pitch) passes the check, the full detector's is refused naming the binning."""
    from astropy.io import fits

    full = NOMINAL
    image = _image(*full.image_size_px, seed=3)
    binned = image.reshape(512, 2, 512, 2).sum(axis=(1, 3))
    fits.PrimaryHDU(binned.astype(np.int32)).writeto(tmp_path / "b.fits")
    assert (
        main(["centroid", str(tmp_path / "b.fits"), "--time-unknown", "--quiet", "--out", str(tmp_path / "b.csv")]) == 0
    )
    session = read_session(tmp_path / "b.csv")
    x0, y0 = full.principal_point_px
    half = replace(
        full,
        image_size_px=(512, 512),
        pixel_pitch_um=2 * full.pixel_pitch_um,
        principal_point_px=((x0 - 0.5) / 2, (y0 - 0.5) / 2),
    )
    check_on_detector(session, half.image_size_px, "b.csv", "half.json")  # passes
    with pytest.raises(
        UserError,
        match=r"512 x 512 px \(frame 0\) but the detector of full.json is 1024 x 1024 px; "
        r"binned 2 x 2\?",
    ):
        check_on_detector(session, full.image_size_px, "b.csv", "full.json")


@pytest.mark.parametrize(
    ("width", "height", "reason"),
    [
        ("12.5", "960", "column image_width_px: expected a whole number of pixels"),
        ("0", "960", "column image_width_px: expected a whole number of pixels"),
        ("1280", "-3", "column image_height_px: expected a whole number of pixels"),
        ("1280", "big", "column image_height_px: not a number: 'big'"),
        ("1280", "", "image_width_px and image_height_px must both be given or both empty"),
    ],
)
def test_a_bad_image_size_cell_is_refused_naming_the_line(tmp_path, width, height, reason):
    rows = ["frame,t_utc,star_id,x_px,y_px,image_width_px,image_height_px", "0,,0,10,20,1280,960"]
    rows.append(f"1,,0,10,20,{width},{height}")
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(UserError, match=f"s.csv: line 3, {reason}" if "column" in reason else f"line 3: {reason}"):
        read_session(tmp_path / "s.csv")


def test_one_image_size_column_without_the_other_is_refused(tmp_path):
    (tmp_path / "s.csv").write_text("frame,t_utc,star_id,x_px,y_px,image_width_px\n0,,0,10,20,1280\n")
    with pytest.raises(UserError, match="image_width_px and image_height_px must both be present or both absent"):
        read_session(tmp_path / "s.csv")


def test_rows_whose_size_is_empty_are_not_checked_so(tmp_path):
    """Empty cells: the size of that image is not known; those rows are checked by position alone."""
    text = "frame,t_utc,star_id,x_px,y_px,image_width_px,image_height_px\n0,,0,10,20,,\n1,,0,10,20,1024,1024\n"
    (tmp_path / "s.csv").write_text(text)
    session = read_session(tmp_path / "s.csv")
    np.testing.assert_array_equal(image_sizes_px(session), [[0, 0], [1024, 1024]])
    check_on_detector(session.select(np.array([0])), WIDER.image_size_px, "s", "wider")  # unknown: passes
    with pytest.raises(UserError, match=r"frame 1\) but the detector of wider is 1280 x 1024 px"):
        check_on_detector(session, WIDER.image_size_px, "s", "wider")


sides = st.integers(min_value=1, max_value=1 << 24)


@settings(max_examples=60, deadline=None)
@given(width=sides, height=sides, other_width=sides, other_height=sides, parquet=st.booleans())
def test_the_image_size_reads_back_as_written_and_is_checked_exactly(
    tmp_path_factory, width, height, other_width, other_height, parquet
):
    """Any detector size (1..2^24 px a side, as parameter files allow) is written and read back the same, through
    CSV or Parquet, a selection and a join of frames; the check passes for the same size only."""
    n = 3
    rows = Session(np.array([0, 0, 1]), np.full(n, "", object), np.zeros(n, np.int64), np.zeros(n), np.zeros(n))
    session = _with_size(rows, width, height)
    path = tmp_path_factory.mktemp("p") / ("s.parquet" if parquet else "s.csv")
    write_session(path, concatenate_sessions([session.select(np.arange(2)), session.select(np.array([2]))]))
    back = read_session(path)
    np.testing.assert_array_equal(image_sizes_px(back), np.tile([width, height], (n, 1)))
    check_on_detector(back, (width, height), "s", "p")
    if (other_width, other_height) != (width, height):
        with pytest.raises(UserError, match=f"its images are {width} x {height} px"):
            check_on_detector(back, (other_width, other_height), "s", "p")
