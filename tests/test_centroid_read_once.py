"""``--median-of-inputs`` decodes each image once: the images read for the median are the ones centroided
(hostlink.images.centroid.session, ``_KEEP_READ_BYTES``), with the same session as when each is read again."""

import numpy as np

from hostlink.images.centroid import CentroidOptions, TimeOptions, centroid_images
from hostlink.images.centroid import session as centroid_session
from hostlink.sky.render import pixel_integrated_gaussian


def _frames(tmp_path, count: int = 3) -> list:
    """``count`` 16-bit frames of white noise with five stars each, at other places in every frame (a median of
    frames at different pointings holds none of them)."""
    import tifffile

    rng = np.random.default_rng(5)
    rows, cols = np.arange(96.0), np.arange(128.0)
    paths = []
    for k in range(count):
        image = 1000.0 + rng.normal(0.0, 10.0, (96, 128))
        for x, y in rng.uniform(12.0, 84.0, (5, 2)):
            star = np.outer(pixel_integrated_gaussian(rows, y, 1.2), pixel_integrated_gaussian(cols, x, 1.2))
            image += 20000.0 * star
        path = tmp_path / f"f{k}.tif"
        tifffile.imwrite(path, np.clip(image, 0, 65535).astype(np.uint16))
        paths.append(path)
    return paths


def test_median_of_inputs_reads_each_image_once(tmp_path, monkeypatch):
    paths = _frames(tmp_path)
    reads = []
    read = centroid_session.read_image
    monkeypatch.setattr(centroid_session, "read_image", lambda path: reads.append(path) or read(path))
    options, times = CentroidOptions(median_of_inputs=True), TimeOptions(time_unknown=True)
    once = centroid_images(paths, options, times).session
    assert sorted(reads) == sorted(paths)  # each once: for the median, then centroided as read
    reads.clear()
    monkeypatch.setattr(centroid_session, "_KEEP_READ_BYTES", 0)  # none kept: each read again to be centroided
    twice = centroid_images(paths, options, times).session
    assert sorted(reads) == sorted(paths + paths)
    assert len(once) >= 3 * 4  # the stars were found (most of the five per frame)
    for column in ("frame", "x_px", "y_px", "mag"):
        np.testing.assert_array_equal(getattr(once, column), getattr(twice, column))  # the same pixels, bit for bit
    assert once.extra.keys() == twice.extra.keys()
    for name in once.extra:
        np.testing.assert_array_equal(once.extra[name], twice.extra[name])
