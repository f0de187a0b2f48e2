"""Issue 30, a new user's bad input to ``hostlink centroid``: a truncated JPEG, an empty file and a blank frame each
end in one line on stderr with exit 2, no traceback, and no session written (scripts/newcamera.py tries these and
more on the shared sets: docs/realsky.md, "A new camera: what was tried")."""

import numpy as np
import pytest
from PIL import Image

from hostlink.cli import main
from hostlink.sky.render import RenderConfig, render_stars


def _jpeg(path, size=(320, 240)):
    rng = np.random.default_rng(1)
    x, y = rng.uniform(10, size[0] - 10, 20), rng.uniform(10, size[1] - 10, 20)
    rendered = render_stars(x, y, np.full(20, 20000.0), size, RenderConfig(bits=8, gain_e_per_adu=20.0))
    Image.fromarray(rendered.image_adu.astype(np.uint8)).save(path, quality=90)


def _run(capsys, tmp_path, image) -> tuple[int, list[str]]:
    out = tmp_path / "s.csv"
    code = main(["centroid", str(image), "--time-unknown", "--out", str(out)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert not out.exists() and not list(tmp_path.glob("*.partial"))
    assert "Traceback" not in "\n".join(err)
    return code, err


@pytest.mark.parametrize("kind", ["truncated", "empty"])
def test_an_unreadable_image_is_one_line_naming_it(capsys, tmp_path, kind):
    image = tmp_path / "frame.jpg"
    _jpeg(image)
    image.write_bytes(image.read_bytes()[:600] if kind == "truncated" else b"")
    code, err = _run(capsys, tmp_path, image)
    assert code == 2 and len(err) == 1 and "frame.jpg: cannot read the image" in err[0], err


def test_a_blank_frame_says_so(capsys, tmp_path):
    """An image of one value (a lens cap, a failed readout) is not answered with 'lower --threshold-sigma'."""
    image = tmp_path / "blank.png"
    Image.fromarray(np.zeros((240, 320), np.uint8)).save(image)
    code, err = _run(capsys, tmp_path, image)
    assert code == 2 and len(err) == 1 and "blank" in err[0] and "threshold" not in err[0], err


def test_the_same_frame_readable_gives_stars(capsys, tmp_path):
    """The rendered frame the tests above break is one that centroids (the failures are the damage's)."""
    image = tmp_path / "frame.jpg"
    _jpeg(image)
    assert main(["centroid", str(image), "--time-unknown", "--quiet", "--out", str(tmp_path / "s.csv")]) == 0
    assert (tmp_path / "s.csv").exists()


def test_an_image_of_another_size_is_refused_naming_both(capsys, tmp_path):
    """A PNG of another camera among the frames (another size than the first image) is refused before anything is
    written: a session is one camera's, and identify and calibrate would treat its stars as the first camera's."""
    first, other = tmp_path / "frame.jpg", tmp_path / "other.png"
    _jpeg(first)
    _jpeg(tmp_path / "other.jpg", size=(400, 300))
    Image.open(tmp_path / "other.jpg").save(other)
    out = tmp_path / "s.csv"
    code = main(["centroid", str(first), str(other), "--time-unknown", "--out", str(out)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    assert "other.png: 400 x 300 px, the first image (frame.jpg) is 320 x 240 px" in err[0], err
    assert not out.exists() and not list(tmp_path.glob("*.partial"))


def test_an_image_given_twice_is_refused(capsys, tmp_path):
    """The same file twice (overlapping globs) would be two frames of one exposure, and with --median-of-inputs the
    median would be that frame: its stars subtracted away. Refused in one line, by the file, however it is named."""
    image = tmp_path / "frame.jpg"
    _jpeg(image)
    other = tmp_path / "other.jpg"
    _jpeg(other, size=(320, 240))
    out = tmp_path / "s.csv"
    again = tmp_path / "link.jpg"  # the same file by another name
    again.symlink_to(image)
    code = main(
        ["centroid", str(image), str(other), str(again), "--median-of-inputs", "--time-unknown", "--out", str(out)]
    )
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "link.jpg: given twice (images 1 and 3)" in err[0], err
    assert not out.exists() and not list(tmp_path.glob("*.partial"))
