"""The background and the local noise of a night-sky frame for the source extraction
(:mod:`hostlink.images.centroid`, steps 1-2), made to hold on frames with a horizon: a bright light-polluted glow
(often saturated), black trees or buildings, a strong sky gradient (docs/realsky.md, "Glow and horizon").

1. *Blank regions* (:func:`saturated_regions`): the pixels at the clip level in regions too wide for any star's core
   (a morphological opening by a square of :data:`BLANK_MIN_WIDTH_PX`; a saturated star or planet core is a few PSF
   sigmas across), widened by :data:`BLANK_MARGIN_PX`, hold no star and no noise. They are masked from SEP's
   background mesh (a mesh box mostly masked is interpolated from its neighbours, Bertin & Arnouts 1996, sec. 3.1)
   and from the detection.
2. *Local noise and offset* (:func:`local_noise_map`): SEP's noise map assumes independent Gaussian pixel noise; an
   8-bit camera clips it at zero, a JPEG correlates neighbouring pixels. What the detection filter actually sees is
   measured on the filtered image in each mesh box, as (P97.725 - P50) / 2 (half the distance from the median to the
   upper 2-sigma point of a Gaussian: blind to the clipped lower half, and counting the heavier upper tail of clipped
   or JPEG noise that decides the false detections), the stars' light left out (:func:`_clipped_box_noise`: once
   stars fill 2.3 % of a box their light is its upper 2-sigma point), converted to the per-pixel noise of
   independent pixels that gives it (divided by sqrt(sum k^2) of the normalised kernel); what SEP's mesh leaves of
   the background, as the median of the filtered image in boxes 4 x finer. Each is the median over 5 x 5 of its
   boxes (a box a bright star or the step of a horizon fills is outvoted), interpolated bilinearly between the box
   centres. Both were global before (one percentile over the whole frame): a glow or a gradient then raised the
   threshold of the whole frame (docs/realsky.md).
3. *Steps* (:func:`_step_offset`): where the fine boxes' medians depart from that smooth offset by more than
   :data:`_EDGE_OFFSET_SIGMAS` (a horizon, a roof line: SEP's mesh straddles the step and overshoots on one side),
   they are the offset; the boxes of the step itself, along a line at least :data:`_STEP_MIN_LENGTH_BOXES` long, are
   not searched.

Every value of the noise map is finite and positive where any box was measurable (a box wholly masked takes its
nearest measured neighbour's value), so every star's ``sigma_px`` is.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hostlink.images.order_statistics import row_percentiles, sorted_row_percentiles

#: A region at the clip level narrower than this [px] in either direction is a star's or a planet's core, not a
#: blank region (the rendered 50-deg set's brightest planet, Hp -4 with a PSF of 2.6 px at the corner, saturates a
#: disc ~20 px across; the horizon glow of the same set spans the frame).
BLANK_MIN_WIDTH_PX = 41
#: Holes narrower than this [px] in a clipped region are filled (a JPEG's 8 x 8 blocks leave pixels at 254 in a
#: region clipped at 255; a gap between two saturated stars is wider than that only when they are 9 px apart).
_HOLE_WIDTH_PX = 9
#: A blank region is widened by this much [px]: its edge, blurred by the optics and rung by the JPEG's 8 x 8 blocks,
#: stays a few steps below the clip level over up to ~10 px (the rendered glow of tests/test_images_glow.py).
BLANK_MARGIN_PX = 16
#: A mesh box is measured when at least this fraction of its pixels is unmasked.
_MIN_BOX_FRACTION = 0.25
#: The noise and the smooth offset are medians over this many fine boxes square (module docstring).
_SMOOTH_BOXES = 5
#: The noise and offset boxes are this many times finer than the mesh's, and at least this wide [px].
_FINE_BOXES_PER_BOX = 4
_MIN_FINE_BOX_PX = 8
#: A fine box's residual is an edge's when beyond this many noise sigmas of the filtered image.
_EDGE_OFFSET_SIGMAS = 1.0
#: Two adjacent fine boxes whose edge offsets have opposite signs and differ by more than this many noise sigmas of
#: the filtered image hold a step between them: nothing is detected there (the bilinear offset leaves up to half the
#: step on its bright side).
_EDGE_STEP_SIGMAS = 3.0
#: A step's boxes are not searched only where they extend over this many fine boxes (module docstring, :func:`_long`).
_STEP_MIN_LENGTH_BOXES = 8
#: A noise below this many float32 epsilons of the background level is SEP's rounding, not noise (a flat image).
_ROUNDING_NOISE_EPS = 100.0
#: The upper 2-sigma point of a Gaussian [percent]: (P97.725 - P50) / 2 is its sigma.
_UPPER_2SIGMA_PERCENT = 97.725
#: A connected region of the filtered image above this many noise sigmas over the local offset is a star's light when
#: it holds a pixel above :data:`_STAR_PEAK_SIGMAS` (the default detection threshold: Gaussian noise reaches it once
#: in 3.5 million pixels); the region reaches down to 1 sigma, so that what a star leaves outside it needs the noise
#: to add more than 1 sigma to reach the upper 2-sigma point the noise is measured at.
_STAR_ISOPHOTE_SIGMAS = 1.0
_STAR_PEAK_SIGMAS = 5.0
#: The noise is measured again without the stars' light until no smoothed box changes by more than this fraction
#: (the percentiles' own scatter is ~1 %), at most :data:`_MAX_NOISE_PASSES` times (4 passes on a frame with a star
#: every 30 px: docs/realsky.md, "Glow and horizon").
_NOISE_CONVERGED_FRACTION = 0.01
_MAX_NOISE_PASSES = 6

#: :func:`_star_light` looks its regions' labels up this many pixels at a time (their intp copy: 8 MB).
_TAKE_STRIP_ELEMENTS = 1 << 20


def saturated_regions(raw: np.ndarray, saturation_adu: float | None) -> np.ndarray:
    """(h, w) bool: the pixels of ``raw`` at or above ``saturation_adu``, their holes narrower than
    :data:`_HOLE_WIDTH_PX` filled (a closing: a JPEG leaves pixels one step below the clip level inside a clipped
    region), that lie in a region of them at least :data:`BLANK_MIN_WIDTH_PX` wide (an opening by that square: erosion
    then dilation, each separable into a minimum and a maximum filter), widened by :data:`BLANK_MARGIN_PX` (its
    edge, blurred by the optics and the JPEG, is not sky either). None (no clip level known): nothing."""
    from scipy import ndimage

    if saturation_adu is None:
        return np.zeros(raw.shape, dtype=bool)
    clipped = (raw >= saturation_adu).astype(np.uint8)
    if not _may_hold_blank(clipped):
        return np.zeros(raw.shape, dtype=bool)
    closed = ndimage.minimum_filter(ndimage.maximum_filter(clipped, _HOLE_WIDTH_PX), _HOLE_WIDTH_PX)
    eroded = ndimage.minimum_filter(closed, BLANK_MIN_WIDTH_PX)
    if not eroded.any():  # the dilation of nothing is nothing
        return np.zeros(raw.shape, dtype=bool)
    return widened(ndimage.maximum_filter(eroded, BLANK_MIN_WIDTH_PX).astype(bool))


def _may_hold_blank(clipped: np.ndarray) -> bool:
    """False when no region of :func:`saturated_regions` can exist (the common frame, whose clipped pixels are a few
    star cores): a square of ``BLANK_MIN_WIDTH_PX`` after the closing lies within the clipped pixels dilated by half
    the hole width, so each pixel of it has a clipped pixel within ``_HOLE_WIDTH_PX // 2`` px; the square holds every
    pixel of at least k x k whole aligned blocks of ``_HOLE_WIDTH_PX`` (k = (width - hole + 1) // hole), and the
    centre of each has its clipped pixel within its own block. No k x k group of blocks each holding a clipped pixel:
    no blank region (a necessary condition; the full opening decides otherwise)."""
    from scipy import ndimage

    if not clipped.any():
        return False
    b = _HOLE_WIDTH_PX
    k = (BLANK_MIN_WIDTH_PX - b + 1) // b
    h, w = clipped.shape
    ny, nx = -(-h // b), -(-w // b)
    padded = np.zeros((ny * b, nx * b), dtype=np.uint8)
    padded[:h, :w] = clipped
    # along the columns of blocks first (a reduction across whole rows), then within each block's row: the same
    # maxima as over both block axes at once, faster (docs/realsky.md, "Time")
    occupied = padded.reshape(ny, b, nx * b).max(axis=1).reshape(ny, nx, b).max(axis=2)
    if ny < k or nx < k:
        return bool(occupied.any())
    return bool(ndimage.minimum_filter(occupied, size=k, mode="constant", cval=0).any())


def widened(mask: np.ndarray, margin_px: int = BLANK_MARGIN_PX) -> np.ndarray:
    """``mask`` grown by ``margin_px`` in every direction (a maximum filter of the square 2 margin + 1)."""
    from scipy import ndimage

    if not mask.any():
        return mask.copy()
    return ndimage.maximum_filter(mask.astype(np.uint8), 2 * margin_px + 1).astype(bool)


def local_noise_map(
    filtered: np.ndarray,
    sep_rms: np.ndarray | Callable[[], np.ndarray],
    kernel_norm: float,
    box_px: int,
    mask: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offset map [ADU], noise map [ADU], the pixels of a sharp step where nothing is detected) of the module
    docstring, step 2. ``filtered``: the image less SEP's background, filtered by the detection kernel normalised to
    unit sum; ``sep_rms``: SEP's noise map, or what makes it (``sep.Background.rms``: used only when no box is
    measurable, so that the common frame never spends the time of a full-frame map on it); ``kernel_norm``:
    sqrt(sum k^2) of that kernel; ``box_px``: the mesh box; ``mask``: pixels not measured (blank regions).

    The offset is measured in boxes :data:`_FINE_BOXES_PER_BOX` times finer than the mesh (the median of each), the
    noise in the mesh's boxes (P50 and P97.725, the stars' light left out: :func:`_clipped_box_noise`); each is then
    the median over 5 x 5 of its boxes (a bright star, or the line of boxes a horizon's step crosses, fills fewer than
    half of them, and the median of a smooth gradient is its centre value; SEP's own noise map, the clipped standard
    deviation of each mesh box's pixels, counts a gradient or a step within the box as noise, and its spline swings
    negative next to a masked box); the step's offset (:func:`_step_offset`) is added."""
    h, w = filtered.shape
    fine = max(_MIN_FINE_BOX_PX, box_px // _FINE_BOXES_PER_BOX)
    stats, row_centres, col_centres = _box_percentiles(filtered, mask, fine, (50.0,))
    # the noise from the mesh's boxes: the upper percentile of a fine box's few independent pixels (the JPEG and the
    # filter correlate ~9 neighbours) is biased low (-7 % on the clean frame of tests/test_images_glow.py; half the
    # mesh: 8 false detections instead of 5 on the clipped 8-bit noise of tests/test_images_centroid.py)
    noise, noise_rows, noise_cols = _clipped_box_noise(filtered, mask, stats[..., 0], fine, box_px)  # smoothed
    if noise is None:  # nothing measurable: SEP's map as it is, no offset
        rms = sep_rms() if callable(sep_rms) else sep_rms
        return np.zeros_like(filtered), _positive(rms), np.zeros(filtered.shape, dtype=bool)
    medians, noise = _filled(stats[..., 0]), noise / kernel_norm
    noise_map = _bilinear(noise, noise_rows, noise_cols, h, w)
    # a pixel's value is a weighted mean of its boxes' (weights >= 0, summing to 1): positive where they all are
    if not (np.isfinite(noise).all() and np.all(noise > 0)):
        noise_map = _positive(noise_map)
    smooth = _median(medians, _SMOOTH_BOXES)
    filtered_noise = (
        noise_map[np.rint(row_centres).astype(int)[:, None], np.rint(col_centres).astype(int)] * kernel_norm
    )
    step_offset, step = _step_offset(_median(medians, 3) - smooth, filtered_noise)
    offset_map = _bilinear(smooth + step_offset, row_centres, col_centres, h, w)
    edge = _box_constant(step, fine, (h, w))  # the boxes start at pixel 0
    return offset_map, noise_map, edge


def _clipped_box_noise(
    filtered: np.ndarray, mask: np.ndarray, fine_medians: np.ndarray, fine_px: int, box_px: int
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """The noise of the filtered image in each mesh box, (P97.725 - P50) / 2 of its pixels outside ``mask`` and
    outside the stars' light, median-filtered over 5 x 5 boxes (None where no box is measurable:
    :func:`_box_percentiles`), and the boxes' centres. An iterative clipping of whole stars (as SEP clips single
    pixels at 3 sigma for its own map, Bertin & Arnouts 1996, sec. 3.1, but of the upper side only: the lower half is
    the 8-bit floor's): the stars are the regions
    :func:`_star_light` finds with the noise of the pass before (the first pass counts every pixel: its noise is too
    high where stars are dense, so its clipping keeps their faint wings, and each pass clips deeper), until the noise
    smoothed over 5 x 5 boxes settles (:data:`_NOISE_CONVERGED_FRACTION`). Noise alone loses nearly nothing: a region
    needs a peak at 5 sigma (the heavier tail of clipped 8-bit noise reaches it about as often as it makes a false
    detection). ``fine_medians``: the medians of the fine boxes of ``fine_px`` (the offset the stars stand above).

    The boxes are laid out once (:func:`_boxes`); a pass takes the percentiles of the pixels left in each
    (:func:`_masked_box_percentiles`: the same numbers as :func:`_box_percentiles`, sorting again only the boxes
    whose pixels left changed since the pass before), read from ``filtered`` itself (no float32 copy of the frame
    beside the sorted one); the passes' masks are padded to whole boxes (the padding masked), the filtered image less
    its offset is formed a strip of rows at a time (:func:`_star_light`), not as a frame. Each pass labels the whole
    frame again: its thresholds change in most boxes, and a region's membership depends on the threshold of every box
    it crosses (docs/realsky.md, "The noise map's passes")."""
    boxes = _boxes(filtered, box_px)
    h, w = filtered.shape
    masked = np.ones(boxes.padded_shape, dtype=bool)
    masked[:h, :w] = mask
    excluded = masked
    previous, light = None, None
    for k in range(_MAX_NOISE_PASSES):
        spread = _masked_box_percentiles(boxes, excluded, (50.0, _UPPER_2SIGMA_PERCENT))
        rows, cols = boxes.row_centres, boxes.col_centres
        noise = 0.5 * (spread[..., 1] - spread[..., 0])
        if not np.isfinite(noise).any():  # nothing measurable (or, after the first pass, nothing left: keep it)
            return (None, rows, cols) if previous is None else previous
        smooth = _median(_filled(noise), _SMOOTH_BOXES)
        if k + 1 == _MAX_NOISE_PASSES or (
            previous is not None and np.all(np.abs(smooth - previous[0]) <= _NOISE_CONVERGED_FRACTION * previous[0])
        ):
            break
        previous = (smooth, rows, cols)
        if light is None:  # the buffers of every pass, allocated once (docs/realsky.md, "Large frames")
            light = _StarLightBuffers(
                np.zeros(boxes.padded_shape, dtype=bool),
                np.zeros(boxes.padded_shape, dtype=bool),
                np.empty(boxes.padded_shape, dtype=np.int32),
                np.empty(boxes.padded_shape, dtype=bool),
            )
            fine_offset = _filled(fine_medians)
        excluded = _star_light(filtered, fine_offset, fine_px, masked, smooth, box_px, light)
        excluded |= masked
    return smooth, rows, cols


def _box_constant(grid: np.ndarray, box_px: int, shape: tuple[int, int]) -> np.ndarray:
    """The box values ``grid`` spread over an image of ``shape``, each constant over its box of ``box_px`` from
    pixel 0."""
    h, w = shape
    return np.repeat(np.repeat(grid, box_px, axis=0), box_px, axis=1)[:h, :w]


@dataclass(frozen=True)
class _StarLightBuffers:
    """The (padded h, padded w) arrays :func:`_star_light` writes in each pass of :func:`_clipped_box_noise`, allocated
    once: ``isophote`` and ``peaks`` bool (False beyond the image, never written), ``labels`` int32 (the regions),
    ``light`` bool (the pass's result)."""

    isophote: np.ndarray
    peaks: np.ndarray
    labels: np.ndarray
    light: np.ndarray


def _star_light(
    filtered: np.ndarray,
    offset: np.ndarray,
    offset_px: int,
    mask: np.ndarray,
    noise: np.ndarray,
    noise_px: int,
    buffers: _StarLightBuffers,
) -> np.ndarray:
    """(padded h, padded w) bool, ``buffers.light``: the pixels of ``filtered`` less ``offset`` (per box of
    ``offset_px`` from pixel 0: the filtered image over its offset) outside ``mask`` in a connected region
    (8-connected) above :data:`_STAR_ISOPHOTE_SIGMAS` x ``noise`` that holds a pixel above :data:`_STAR_PEAK_SIGMAS`
    x ``noise`` (a star, down to its 1-sigma isophote); ``noise`` per box of ``noise_px`` from pixel 0, constant over
    each box. ``mask`` is (padded h, padded w), the padding beyond ``filtered`` masked. The difference and the
    comparisons are formed a strip of rows at a time, each strip within one row of offset boxes and one of noise boxes
    (the same differences and comparisons as over the whole frame: each strip's offsets and thresholds are one row of
    values, broadcast over its rows), so no frame-sized float array is made (docs/realsky.md, "Large frames")."""
    from scipy import ndimage

    h, w = filtered.shape
    isophote, peaks, labels = buffers.isophote, buffers.peaks, buffers.labels
    isophote_thresholds = np.repeat(_STAR_ISOPHOTE_SIGMAS * noise, noise_px, axis=1)[:, :w]
    peak_thresholds = np.repeat(_STAR_PEAK_SIGMAS * noise, noise_px, axis=1)[:, :w]
    offsets = np.repeat(offset, offset_px, axis=1)[:, :w]
    edges = np.union1d(np.arange(0, h, offset_px), np.arange(0, h, noise_px))
    above = np.empty((min(offset_px, noise_px), w))
    for start, stop in zip(edges, [*edges[1:], h], strict=True):
        strip = above[: stop - start]
        np.subtract(filtered[start:stop], offsets[start // offset_px], out=strip)
        np.greater(strip, isophote_thresholds[start // noise_px], out=isophote[start:stop, :w])
        np.greater(strip, peak_thresholds[start // noise_px], out=peaks[start:stop, :w])
        isophote[start:stop, :w] &= ~mask[start:stop, :w]
    n = ndimage.label(isophote, structure=np.ones((3, 3), dtype=int), output=labels)
    star = np.zeros(n + 1, dtype=bool)
    star[labels[peaks]] = True
    star[0] = False
    # star[labels] into the pass's buffer, a strip at a time: take converts its indices to intp (a frame of them
    # would be 8 bytes a pixel); mode "clip" (every label is in range) writes to out directly
    light, rows = buffers.light, max(1, _TAKE_STRIP_ELEMENTS // labels.shape[1])
    for start in range(0, labels.shape[0], rows):
        np.take(star, labels[start : start + rows], out=light[start : start + rows], mode="clip")
    return light


@dataclass(frozen=True)
class _Boxes:
    """The pixels of an image in boxes from pixel (0, 0) (:func:`_boxes`): ``image`` the image itself (float64, not
    copied: :func:`_box_row_values` reads a row of boxes from it when a pass needs it); ``inside`` each box's number
    of pixels within the image; the boxes' grid shape, the shape of the image padded to whole boxes, and the boxes'
    centres [px]. ``work``: each box's pixels left by the last pass (boxes, box^2) float32, sorted (NaN last),
    ``work_gone`` the pixels that pass excluded (boxes, box^2) bool and ``work_counted`` each box's number left,
    updated in place by :func:`_masked_box_percentiles` (at first every pixel excluded, none left: a state as
    consistent as any other)."""

    image: np.ndarray
    work: np.ndarray
    work_gone: np.ndarray
    work_counted: np.ndarray
    inside: np.ndarray
    grid_shape: tuple[int, int]
    padded_shape: tuple[int, int]
    row_centres: np.ndarray
    col_centres: np.ndarray


def _box_grid(h: int, w: int, box_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each box's number of pixels within an (h, w) image, (boxes,), and the boxes' centres, rows and columns [px],
    for boxes of ``box_px`` from pixel (0, 0) (the last row and column of boxes cut by the border)."""
    ny, nx = -(-h // box_px), -(-w // box_px)
    inside = np.outer(np.minimum(box_px, h - np.arange(ny) * box_px), np.minimum(box_px, w - np.arange(nx) * box_px))
    row_centres = np.minimum(np.arange(ny) * box_px + 0.5 * (box_px - 1), 0.5 * (np.arange(ny) * box_px + h - 1))
    col_centres = np.minimum(np.arange(nx) * box_px + 0.5 * (box_px - 1), 0.5 * (np.arange(nx) * box_px + w - 1))
    return inside.ravel(), row_centres, col_centres


def _box_blocks(image: np.ndarray, mask: np.ndarray, box_px: int):
    """The unmasked pixels of ``image`` per box of ``box_px`` from pixel (0, 0), (boxes, box^2) float32 with NaN for
    masked pixels and beyond the image; each box's number of pixels within the image; the boxes' centres, rows and
    columns [px] (the last row and column of boxes cut by the border)."""
    h, w = image.shape
    ny, nx = -(-h // box_px), -(-w // box_px)
    # float32: half the memory; the percentiles' own scatter (~1 % of the noise) is far above its rounding
    padded = np.full((ny * box_px, nx * box_px), np.nan, dtype=np.float32)
    padded[:h, :w] = image
    padded[:h, :w][mask] = np.nan
    blocks = padded.reshape(ny, box_px, nx, box_px).transpose(0, 2, 1, 3).reshape(ny * nx, -1)
    return (blocks, *_box_grid(h, w, box_px))


def _box_row_values(out: np.ndarray, image: np.ndarray, box_row: int, box_px: int) -> np.ndarray:
    """``out`` (boxes of the row, box^2) float32: the pixels of ``image`` in each box of row ``box_row`` of boxes of
    ``box_px`` from pixel (0, 0), NaN beyond the image; the numbers of :func:`_box_blocks`' rows (the same float32
    rounding), without a padded copy of the frame."""
    h, w = image.shape
    nx = out.shape[0]
    start = box_row * box_px
    strip = image[start : min(h, start + box_px)]
    n_rows, whole = strip.shape[0], w // box_px
    boxes = out.reshape(nx, box_px, box_px).transpose(1, 0, 2)  # (row within the box, box, column within the box)
    boxes[:n_rows, :whole] = strip[:, : whole * box_px].reshape(n_rows, whole, box_px)
    if whole < nx:
        boxes[:n_rows, whole, : w - whole * box_px] = strip[:, whole * box_px :]
        boxes[:n_rows, whole, w - whole * box_px :] = np.nan
    boxes[n_rows:] = np.nan
    return out


def _boxes(image: np.ndarray, box_px: int) -> _Boxes:
    """The :class:`_Boxes` of the pixels of ``image`` in boxes of ``box_px``, laid out once for every pass of
    :func:`_clipped_box_noise` (which pixels are masked each pass says: :func:`_masked_box_percentiles`)."""
    h, w = image.shape
    inside, row_centres, col_centres = _box_grid(h, w, box_px)
    grid = (row_centres.size, col_centres.size)
    padded = (grid[0] * box_px, grid[1] * box_px)
    work = np.full((grid[0] * grid[1], box_px * box_px), np.nan, dtype=np.float32)
    work_gone = np.ones(work.shape, dtype=bool)
    none_left = np.zeros(work.shape[0], dtype=np.int64)
    return _Boxes(image, work, work_gone, none_left, inside, grid, padded, row_centres, col_centres)


def _masked_box_percentiles(boxes: _Boxes, excluded: np.ndarray, percents: tuple[float, ...]) -> np.ndarray:
    """(ny, nx, len(percents)): the ``percents`` of each box's pixels not ``excluded`` ((padded h, padded w) bool,
    holding the masked pixels and those beyond the image), NaN for a box whose pixels left are fewer than
    :data:`_MIN_BOX_FRACTION` of those within the image: :func:`_box_percentiles`' numbers
    (:func:`sorted_row_percentiles` of the pixels left, sorted). Only the boxes whose pixels left differ from the
    last pass's (``boxes.work_gone``) are sorted again: in the later passes of :func:`_clipped_box_noise` the stars'
    light changes in a few boxes (docs/realsky.md, "The noise map's passes"); the others keep their sorted pixels,
    the same numbers."""
    ny, nx = boxes.grid_shape
    box_px = boxes.padded_shape[0] // ny
    gone = excluded.reshape(ny, box_px, nx, box_px).transpose(0, 2, 1, 3).reshape(ny * nx, -1)
    changed = (gone != boxes.work_gone).any(axis=1)
    if changed.any():
        # each row of boxes read from the image, its changed boxes sorted (the first pass: every box, in place in
        # the work array)
        for box_row in np.flatnonzero(changed.reshape(ny, nx).any(axis=1)):
            row = slice(box_row * nx, (box_row + 1) * nx)
            if changed[row].all():
                _sort_left(_box_row_values(boxes.work[row], boxes.image, box_row, box_px), gone[row])
            else:
                picked = row.start + np.flatnonzero(changed[row])
                values = _box_row_values(np.empty((nx, box_px * box_px), np.float32), boxes.image, box_row, box_px)
                boxes.work[picked] = _sort_left(values[picked - row.start], gone[picked])
    if changed.all():
        np.copyto(boxes.work_gone, gone)
        boxes.work_counted[:] = gone.shape[1] - np.count_nonzero(gone, axis=1)
    elif changed.any():
        rows = np.flatnonzero(changed)
        boxes.work_gone[rows] = gone[rows]
        boxes.work_counted[rows] = gone.shape[1] - np.count_nonzero(gone[rows], axis=1)
    counted = boxes.work_counted
    out = np.full((ny * nx, len(percents)), np.nan)
    measurable = _measurable(counted, boxes.inside)
    if measurable.any():
        ordered = boxes.work if measurable.all() else boxes.work[measurable]
        out[measurable] = sorted_row_percentiles(ordered, percents, counted[measurable])
    return out.reshape(ny, nx, len(percents))


def _sort_left(values: np.ndarray, gone: np.ndarray) -> np.ndarray:
    """``values`` (rows, n) float32, in place: each row with its ``gone`` pixels NaN, sorted (NaN last)."""
    np.copyto(values, np.float32(np.nan), where=gone)
    values.sort(axis=1)
    return values


def _step_offset(residual: np.ndarray, filtered_noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the smooth offset leaves at a sharp edge (a horizon, a roof line), per fine box: ``residual``, the boxes'
    medians median-filtered over 3 x 3 (a step passes a median filter unchanged, a star filling one or a few boxes
    does not) less the smooth offset, kept where beyond :data:`_EDGE_OFFSET_SIGMAS` x the filtered image's noise (a
    fine box's median scatters by ~0.15 of it: a clean frame keeps none, its offset is the smooth one alone). Within
    the boxes of the step itself no smooth background holds (the bilinear interpolation between the boxes leaves part
    of the step on its bright side): the second value marks the boxes whose 3 x 3 neighbourhood's medians span more
    than :data:`_EDGE_STEP_SIGMAS` x that noise, where nothing is detected."""
    kept = np.where(np.abs(residual) > _EDGE_OFFSET_SIGMAS * filtered_noise, residual, 0.0)
    if not kept.any():
        return kept, np.zeros(kept.shape, dtype=bool)
    return kept, _long(_median_span(residual) > _EDGE_STEP_SIGMAS * filtered_noise)


def _long(step: np.ndarray) -> np.ndarray:
    """``step`` keeping only its connected parts (8-connected) that extend over at least
    :data:`_STEP_MIN_LENGTH_BOXES` boxes along a row or a column: a horizon or a roof line, not the halo of a bright
    star (which bends the offset in a compact patch: on granasat's pleyades_8sec, patches of 1 x 1 to 4 x 2 boxes,
    one holding a saturated star)."""
    from scipy import ndimage

    if not step.any():
        return step
    labels, _ = ndimage.label(step, structure=np.ones((3, 3), dtype=int))
    keep = np.zeros(labels.max() + 1, dtype=bool)
    for k, part in enumerate(ndimage.find_objects(labels), start=1):
        keep[k] = max(part[0].stop - part[0].start, part[1].stop - part[1].start) >= _STEP_MIN_LENGTH_BOXES
    return keep[labels]


def _median_span(grid: np.ndarray) -> np.ndarray:
    """The range (maximum - minimum) of ``grid`` over each box's 3 x 3 neighbourhood."""
    from scipy import ndimage

    return ndimage.maximum_filter(grid, size=3, mode="nearest") - ndimage.minimum_filter(grid, size=3, mode="nearest")


def _box_percentiles(
    image: np.ndarray, mask: np.ndarray, box_px: int, percents: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``percents`` of the unmasked pixels of ``image`` in each box of ``box_px`` x ``box_px`` from pixel (0, 0)
    (the last row and column of boxes cut by the border), (ny, nx, len(percents)), NaN for a box whose unmasked
    pixels are fewer than :data:`_MIN_BOX_FRACTION` of its pixels within the image (:func:`_measurable`); and the
    boxes' centres, rows and columns [px]."""
    blocks, inside, row_centres, col_centres = _box_blocks(image, mask, box_px)
    ny, nx = row_centres.size, col_centres.size
    counted = np.isfinite(blocks).sum(axis=1)
    out = np.full((ny * nx, len(percents)), np.nan)
    whole = counted == box_px * box_px
    if whole.all():  # the common case: sorted in place (blocks is this call's own array)
        blocks.sort(axis=1)
        out[:] = sorted_row_percentiles(blocks, percents)
    elif whole.any():
        out[whole] = row_percentiles(blocks[whole], percents)
    part = ~whole & _measurable(counted, inside)
    if part.any():  # boxes cut by the border, a mask or the stars' light (_clipped_box_noise), in one call
        out[part] = row_percentiles(blocks[part], percents, counted[part])
    return out.reshape(ny, nx, len(percents)), row_centres, col_centres


def _measurable(counted: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(boxes,) bool: the boxes whose ``counted`` pixels left hold at least :data:`_MIN_BOX_FRACTION` of their
    ``inside`` pixels within the image, and one at least (the rule of :func:`_box_percentiles` and
    :func:`_masked_box_percentiles`)."""
    return (counted >= _MIN_BOX_FRACTION * inside) & (counted > 0)


def _positive(noise: np.ndarray) -> np.ndarray:
    """``noise`` with its non-positive or non-finite values replaced by the smallest positive finite one (a frame
    whose every pixel is clipped: 1 ADU)."""
    good = np.isfinite(noise) & (noise > 0)
    if good.all():
        return noise
    floor = float(noise[good].min()) if good.any() else 1.0
    return np.where(good, noise, floor)


def _filled(grid: np.ndarray) -> np.ndarray:
    """``grid`` with each NaN box given the value of its nearest finite box (Euclidean distance in boxes)."""
    from scipy import ndimage

    missing = ~np.isfinite(grid)
    if not missing.any():
        return grid
    _, (ri, ci) = ndimage.distance_transform_edt(missing, return_indices=True)
    return grid[ri, ci]


def _median(grid: np.ndarray, size: int) -> np.ndarray:
    """``size`` x ``size`` median filter over the boxes, the grid mirrored beyond its edge without repeating the edge
    box (repeated, a border box that a star inflates weighs 3 of 5 along that axis: the noise 40 % high beside a pair
    of stars at the border of tests/test_sky_render.py's frame, enough to change its centroid)."""
    from scipy import ndimage

    return ndimage.median_filter(grid, size=size, mode="mirror")


def _bilinear(grid: np.ndarray, row_centres: np.ndarray, col_centres: np.ndarray, h: int, w: int) -> np.ndarray:
    """The box values ``grid`` (at the box centres) interpolated bilinearly onto every pixel, constant beyond the
    outermost centres. Separable: along the rows of boxes, then along the columns."""
    return _weights_matrix(h, row_centres) @ grid @ _weights_matrix(w, col_centres).T


def _weights_matrix(n: int, centres: np.ndarray) -> np.ndarray:
    """(n, len(centres)): row i holds the two weights of :func:`_linear_weights` for position i (a matrix product
    with it interpolates a whole frame in a few milliseconds; gathering the pixels' two neighbours takes ~10 x
    longer)."""
    lower, upper, t = _linear_weights(np.arange(n, dtype=np.float64), centres)
    weights = np.zeros((n, centres.size))
    rows = np.arange(n)
    weights[rows, lower] += 1.0 - t
    weights[rows, upper] += t
    return weights


def _linear_weights(at: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each position ``at``: the indices of the two ``centres`` (increasing) around it and the weight of the
    second, clamped to the first and last centre."""
    if centres.size == 1:
        zero = np.zeros(at.size, dtype=np.int64)
        return zero, zero, np.zeros(at.size)
    upper = np.clip(np.searchsorted(centres, at), 1, centres.size - 1)
    lower = upper - 1
    t = np.clip((at - centres[lower]) / (centres[upper] - centres[lower]), 0.0, 1.0)
    return lower, upper, t


def kernel_norm(kernel: np.ndarray) -> float:
    """sqrt(sum k^2) of ``kernel`` normalised to unit sum: the noise of the filtered image per unit of independent
    pixel noise."""
    k = np.asarray(kernel, dtype=np.float64)
    k = k / k.sum()
    return math.sqrt(float(np.sum(k**2)))


def filtered_noise_correction(
    sub: np.ndarray,
    sep_rms: np.ndarray | Callable[[], np.ndarray],
    kernel: np.ndarray,
    box_px: int,
    blank: np.ndarray,
    background_level: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(offset map [ADU], noise map [ADU], filtered image less the offset, pixels where nothing is detected: the
    blank regions widened by :data:`BLANK_MARGIN_PX` and the steps of sharp edges) that make SEP's background and
    noise describe the detection image as it is, box by box (module docstring, step 2). ``sub``: the image less SEP's
    background; ``kernel``: the detection kernel; ``blank``: the blank regions (:func:`saturated_regions`), where the
    filtered image is set to 0 (nothing is searched there, :func:`hostlink.images.centroid._candidates`); ``sep_rms``:
    as :func:`local_noise_map`'s; ``background_level``: SEP's global background [ADU], whose float32 rounding floors
    the noise (:data:`_ROUNDING_NOISE_EPS`)."""
    from scipy import ndimage

    k = np.asarray(kernel, dtype=np.float64)
    filtered = ndimage.convolve(sub, k / k.sum(), mode="nearest")
    offset, noise, edge = local_noise_map(filtered, sep_rms, kernel_norm(k), box_px, blank)
    # a flat image's "noise" is the rounding of SEP's float32 background: not noise
    rounding = _ROUNDING_NOISE_EPS * float(np.finfo(np.float32).eps) * abs(background_level)
    if noise is sep_rms:  # the caller's array, kept as it is
        noise = np.maximum(noise, rounding)
    else:  # the map is this call's own: floored in place (a second frame-sized float64 array at the peak otherwise)
        np.maximum(noise, rounding, out=noise)
    filtered -= offset
    ignored = blank | edge
    if ignored.any():
        filtered[ignored] = 0.0
    return offset, noise, filtered, ignored
