"""``hostlink centroid`` over many images shows progress: :func:`hostlink.api.centroid_images` reports each image
done, and the command passes that to the progress bar with the number of images as its total (the bar itself,
``hostlink.progress``, is silent when stderr is no terminal)."""

import numpy as np
from PIL import Image

from hostlink.api import centroid_images
from hostlink.cli import main
from hostlink.images.centroid.options import TimeOptions
from hostlink.sky.render import RenderConfig, render_stars


def _frames(tmp_path, n: int) -> list[str]:
    rng = np.random.default_rng(3)
    paths = []
    for k in range(n):
        x, y = rng.uniform(10, 310, 20), rng.uniform(10, 230, 20)
        rendered = render_stars(x, y, np.full(20, 20000.0), (320, 240), RenderConfig(bits=8, gain_e_per_adu=20.0))
        path = tmp_path / f"f{k}.png"
        Image.fromarray(rendered.image_adu.astype(np.uint8)).save(path)
        paths.append(str(path))
    return paths


def test_centroid_images_reports_each_image_done(tmp_path):
    done: list[int] = []
    result = centroid_images(_frames(tmp_path, 3), times=TimeOptions(time_unknown=True), progress=done.append)
    assert done == [1, 2, 3] and len(result.frames) == 3


def test_the_command_drives_a_progress_bar_over_the_images(tmp_path, recorded_progress):
    shown = recorded_progress
    paths = _frames(tmp_path, 3)
    assert main(["centroid", *paths, "--time-unknown", "--out", str(tmp_path / "s.csv")]) == 0
    assert shown == [("centroiding images", 3, True, [1, 2, 3])]
    assert main(["centroid", *paths, "--time-unknown", "--quiet", "--out", str(tmp_path / "q.csv")]) == 0
    assert shown[1][2] is False
