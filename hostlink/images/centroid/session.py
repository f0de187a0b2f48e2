"""Many images -> one session of unidentified stars, with a dark, median or median-of-inputs frame subtracted first
(:mod:`hostlink.images.centroid`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import IMAGE_SIZE_COLUMNS, Session, pixel_sigma_text
from hostlink.files.times import parse_iso_utc_many
from hostlink.images.centroid.frame import centroid_pixels
from hostlink.images.centroid.options import Candidates, CentroidOptions, CentroidResult, Detections, TimeOptions
from hostlink.images.centroid.times import _read_times_file, _time_choices, image_time
from hostlink.images.order_statistics import sorted_medians
from hostlink.images.read import RawImage, read_image

#: ``--median-of-inputs`` is refused when the median frame itself holds this many star-like sources (and as many as a
#: frame keeps): the images then share a pointing.
_MEDIAN_MAX_STARS = 5


def centroid_images(
    paths: Sequence[str | Path],
    options: CentroidOptions = CentroidOptions(),  # noqa: B008 (a frozen dataclass)
    times: TimeOptions = TimeOptions(),  # noqa: B008 (a frozen dataclass)
    progress: Callable[[int], None] | None = None,
) -> CentroidResult:
    """Centroid every image in ``paths`` into one session: a frame per image (in time order; in the given order when
    the time is unknown), ``star_id`` 0, ``mag`` the instrumental magnitude, extra columns ``flux_adu``, ``image``
    (file name), ``image_width_px`` and ``image_height_px`` (its size, which identify and calibrate check the nominal
    against) and ``time_source``. Every failure (an unreadable image, no time known for an image, a background
    frame or an image of another size than the first, an image given twice, no star in any image) is a one-line
    :class:`UserError`.
    ``progress(done)`` is called after each image with the number of images done."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise UserError("no image given")
    _check_each_image_once(paths)
    chosen = [k for k, v in _time_choices(times).items() if v]
    if len(chosen) > 1:
        raise UserError(f"give at most one of {', '.join(chosen)}")
    sources = [options.dark, options.median, options.median_of_inputs or None]
    if sum(s is not None for s in sources) > 1:
        raise UserError("give at most one of --dark, --median, --median-of-inputs")
    listed = _read_times_file(Path(times.times_file)) if times.times_file is not None else None
    background, kept = _background_frame(paths, options)

    frames: list[tuple[str, Detections, str, tuple[int, int]]] = []
    blank = 0  # images whose every pixel has one value (a lens cap, no exposure, a failed readout)
    first_size_px: tuple[int, int] | None = None
    for done, path in enumerate(paths, start=1):
        image = kept.pop(path, None) or read_image(path)  # read once: for the median, then here
        first_size_px = first_size_px or image.image_size_px
        _check_same_size(path, image.image_size_px, paths[0], first_size_px)
        blank += int(image.pixels.size == 0 or float(np.ptp(image.pixels)) == 0.0)
        time_utc, source = image_time(image, times, listed)
        det = centroid_pixels(image.pixels, options, background, image.saturation_adu)
        det.report.path = str(path)
        det.report.time_utc, det.report.time_source = time_utc, source
        frames.append((time_utc, det, source, image.image_size_px))
        if progress is not None:
            progress(done)
    if options.median_of_inputs:
        _check_median_holds_no_stars(background, options, [det.report.kept for _, det, *_ in frames])
    if all(det.report.kept == 0 for _, det, *_ in frames):
        if blank == len(paths):
            raise UserError(f"no star found: every pixel of each of the {len(paths)} image(s) has one value (blank)")
        raise UserError(f"no star found in any of the {len(paths)} image(s); lower --threshold-sigma")
    if times.time_unknown:
        order = list(range(len(frames)))
    else:
        jd1, jd2 = parse_iso_utc_many([t for t, *_ in frames])
        order = sorted(range(len(frames)), key=lambda k: (jd1[k] + jd2[k], k))
    return _session([frames[k] for k in order])


def _check_each_image_once(paths: list[Path]) -> None:
    """Refuse a file given twice (overlapping globs, a name typed again): each image is one frame, and a frame twice
    over is counted twice by identify's and calibrate's statistics (and makes the median of ``--median-of-inputs``
    that frame, removing its stars)."""
    first: dict[Path, int] = {}
    for k, path in enumerate(paths):
        j = first.setdefault(path.resolve(), k)
        if j != k:
            raise UserError(f"{path}: given twice (images {j + 1} and {k + 1}); give each image once")


def _check_same_size(path: Path, size_px: tuple[int, int], first: Path, first_size_px: tuple[int, int]) -> None:
    """Refuse an image of another size than the first: a session is one camera's frames, described by one nominal
    (``identify`` and ``calibrate`` take one ``image_size_px``), and a frame of another detector in it would be
    identified and calibrated as if it were the first camera's."""
    if size_px != first_size_px:
        raise UserError(
            f"{path}: {size_px[0]} x {size_px[1]} px, the first image ({first.name}) is {first_size_px[0]} x "
            f"{first_size_px[1]} px: a session holds one camera's frames; centroid each camera's images into a "
            "session of its own"
        )


def _check_median_holds_no_stars(median: np.ndarray, options: CentroidOptions, kept: list[int]) -> None:
    """Refuse ``--median-of-inputs`` on images that share a pointing: their median then holds their stars, and
    subtracting it removes them. The median of frames at different pointings holds at most a few star-like sources
    (warm pixel clusters, a star that stayed put), fewer than :data:`_MEDIAN_MAX_STARS` and fewer than a frame
    keeps."""
    # warm pixels, sharp as an undersampled PSF, are not to pass a footprint matched to the PSF in the median
    in_median = centroid_pixels(
        median, replace(options, max_stars=None, candidate_sigma=None, footprint_follows_psf=False)
    ).report.kept
    per_frame = float(np.mean(kept)) if kept else 0.0
    if in_median >= _MEDIAN_MAX_STARS and in_median >= per_frame:
        raise UserError(
            f"--median-of-inputs: the median of the images holds {in_median} star-like sources (a frame keeps "
            f"{per_frame:.0f}): the images share a pointing and the median would remove their stars; give --dark, "
            "or no background frame"
        )


def _session(frames: list[tuple[str, Detections, str, tuple[int, int]]]) -> CentroidResult:
    """The session of the frames (time, detections, time source, image (width, height) [px]): per frame its stars
    (brightest first), then its candidates (most significant first; ``snr`` set only on them)."""
    parts = [_frame_rows(det) for _, det, *_ in frames]
    counts = [part["x"].size for part in parts]
    n = int(sum(counts))
    frame_no = np.repeat(np.arange(len(frames), dtype=np.int64), counts)

    def cat(name: str) -> np.ndarray:
        return np.concatenate([part[name] for part in parts]) if n else np.zeros(0)

    def repeat(values: list[str]) -> np.ndarray:
        return np.array([v for v, c in zip(values, counts, strict=True) for _ in range(c)], dtype=object)

    flux, snr = cat("flux"), cat("snr")
    extra = {
        "flux_adu": np.array([format(v, ".1f") for v in flux.tolist()], dtype=object),
        "sigma_px": pixel_sigma_text(cat("sigma_px")),
        "saturated": np.array([str(int(v)) for v in cat("saturated").tolist()], dtype=object),
        "blended": np.array([str(int(v)) for v in cat("blended").tolist()], dtype=object),
        "blend_px": pixel_sigma_text(cat("blend_px")),
    }
    if any(det.candidates is not None for _, det, *_ in frames):
        extra["snr"] = _formatted(snr, ".2f")
    extra["image"] = repeat([Path(det.report.path).name for _, det, *_ in frames])
    for axis, name in enumerate(IMAGE_SIZE_COLUMNS):
        extra[name] = repeat([str(size_px[axis]) for *_, size_px in frames])
    extra["time_source"] = repeat([source for _, _, source, _ in frames])
    session = Session(
        frame=frame_no,
        t_utc=repeat([t for t, *_ in frames]),
        star_id=np.zeros(n, np.int64),
        x_px=cat("x"),
        y_px=cat("y"),
        mag=cat("mag"),
        extra=extra,
    )
    return CentroidResult(session, [det.report for _, det, *_ in frames])


def _formatted(values: np.ndarray, spec: str) -> np.ndarray:
    """Each value as text by the format ``spec``, "" where it is not finite (an object array): formatted as Python
    floats (``tolist``): the same text as from numpy's scalars, faster (docs/realsky.md, "Time")."""
    return np.array([format(v, spec) if math.isfinite(v) else "" for v in values.tolist()], dtype=object)


def _frame_rows(det: Detections) -> dict[str, np.ndarray]:
    """One frame's rows of the session: its stars, then its candidates (``snr`` NaN on the stars)."""
    c = det.candidates
    if c is None:
        c = Candidates(*(np.zeros(0) for _ in range(6)))
    return {
        "x": np.concatenate([det.x_px, c.x_px]),
        "y": np.concatenate([det.y_px, c.y_px]),
        "flux": np.concatenate([det.flux_adu, c.flux_adu]),
        "mag": np.concatenate([det.mag, c.mag]),
        "sigma_px": np.concatenate([det.sigma_px, c.sigma_px]),
        "saturated": np.concatenate([det.saturated.astype(np.int64), np.zeros(c.x_px.size, np.int64)]),
        "blended": np.concatenate([det.blended.astype(np.int64), np.zeros(c.x_px.size, np.int64)]),
        "blend_px": np.concatenate([_blend_px(det), np.full(c.x_px.size, np.nan)]),
        "snr": np.concatenate([np.full(det.x_px.size, np.nan), c.snr]),
    }


#: ``--median-of-inputs`` keeps the images it read for the median, to centroid them without decoding them again, while
#: their pixels take at most this many bytes (ten 1.4 Mpx frames: 116 MB; decoding one of those PNGs took 28 ms, a
#: ninth of the openstartracker set's time to centroid: docs/realsky.md, "Speed").
_KEEP_READ_BYTES = 256 * 2**20


def _background_frame(paths: list[Path], options: CentroidOptions) -> tuple[np.ndarray | None, dict[Path, RawImage]]:
    """The frame to subtract from every image (a dark, a median, or the median of the inputs; None) and the input
    images read for it that are kept to be centroided (within :data:`_KEEP_READ_BYTES`; the others are read
    again)."""
    given = options.dark if options.dark is not None else options.median
    if given is not None:
        return read_image(given).pixels, {}
    if not options.median_of_inputs:
        return None, {}
    if len(paths) < 3:
        raise UserError(f"--median-of-inputs needs at least 3 images taken at different pointings, got {len(paths)}")
    stack = None
    kept: dict[Path, RawImage] = {}
    kept_bytes = 0
    for k, path in enumerate(paths):
        image = read_image(path)
        pixels = image.pixels
        if kept_bytes + pixels.nbytes <= _KEEP_READ_BYTES:
            kept[path] = image
            kept_bytes += pixels.nbytes
        if stack is None:
            stack = np.empty((len(paths), *pixels.shape), dtype=np.float32)
        elif pixels.shape != stack.shape[1:]:
            raise UserError(
                f"{path}: {pixels.shape[1]} x {pixels.shape[0]} px, the first image is "
                f"{stack.shape[2]} x {stack.shape[1]} px: --median-of-inputs needs one size"
            )
        stack[k] = pixels
    return _median_frame(stack), kept


#: Elements of the stack :func:`_median_frame` tests for NaN at once (its rows in strips: a boolean temporary of the
#: whole stack is 1.2 GB for 50 frames of 24 Mpx).
_NAN_STRIP_ELEMENTS = 1 << 24


def _median_frame(stack: np.ndarray) -> np.ndarray:
    """``np.median(stack, axis=0)`` as float64, the same numbers for any dtype, from the stack sorted along its first
    axis (:func:`hostlink.images.order_statistics.sorted_medians`: the middle frame's value, or the mean of the
    middle two as ``np.median`` takes it, in float64 for an integer stack): numpy's partition along that axis is
    slower (docs/realsky.md, "Time"). Sorts ``stack`` in place along that axis (each pixel's values reordered, the
    median the same): a sorted copy would hold every frame twice (4.8 GB more for 50 frames of 24 Mpx as float32:
    docs/realsky.md "Large frames"). A stack with a NaN goes to ``np.median`` (which makes its pixel NaN; sorting
    would not)."""
    rows = max(1, _NAN_STRIP_ELEMENTS // max(stack[:, :1].size, 1))
    if any(np.isnan(stack[:, k : k + rows]).any() for k in range(0, stack.shape[1], rows)):
        return np.median(stack, axis=0).astype(np.float64)
    stack.sort(axis=0)
    return sorted_medians(stack, axis=0).astype(np.float64)


def _blend_px(det: Detections) -> np.ndarray:
    """The stars' ``blend_px`` [px] (NaN where not elongated, or where the detections state none)."""
    if det.blend_px is None:
        return np.full(det.x_px.size, np.nan)
    return np.asarray(det.blend_px, dtype=np.float64)
