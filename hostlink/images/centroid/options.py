"""What ``hostlink centroid`` is asked and what it reports: the options, the per-frame report, the stars and
candidates of one image and the session of many (:mod:`hostlink.images.centroid`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.session import Session

#: Centroid methods: the PSF fit (maximum likelihood, the default) or SEP's windowed centroid alone.
CENTROID_METHODS = ("psf-fit", "window")


#: Floor of a saturated star's ``sigma_px`` [px]: its clipped core carries no PSF-fit information and its windowed
#: centroid follows the core's asymmetries: measured 0.33 px per axis over the 446 saturated stars of the granasat
#: JPEG frames after calibration, against 0.19 px for their unsaturated stars (docs/realsky.md).
SATURATED_SIGMA_PX = 0.3


#: Default minimum footprint [filtered pixels above the threshold] (package docstring, step 2).
_DEFAULT_MIN_AREA_PX = 2


#: Default significance down to which candidates are written (package docstring, step 7): the PSF-fit flux over its
#: noise. Candidates only name a star where the calibrated camera predicts one (:mod:`hostlink.images.guided`, which
#: states the chance that noise meets a prediction); below 3 the noise peaks of a frame grow ~10 x per sigma.
DEFAULT_CANDIDATE_SIGMA = 3.0


@dataclass(frozen=True)
class CentroidOptions:
    """How to centroid. ``threshold_sigma``: detection threshold in units of the local background noise;
    ``min_area_px``: minimum footprint [px] above threshold; ``dark`` / ``median``: a frame to subtract first (a file);
    ``median_of_inputs``: subtract the per-pixel median of all the images given (they must be taken at different
    pointings, at least 3); ``saturation_adu``: the clip level (default: from the file, the integer type's maximum);
    ``psf_sigma_px``: the centroid window (default: measured per frame); ``hot_pixel_chi2``, ``max_ellipticity``:
    rejection limits (package docstring, :func:`_hot_pixels`); ``gain_e_per_adu``: the detector's gain, when known, adds
    the stars' own shot noise to the weights of the PSF fit (without it: 1.13-1.17 x the bound instead of 1.0 for stars
    whose shot noise dominates), to ``sigma_px`` and to the noise of the blend test (without it the test counts
    background noise only and rejects about 1 % of moderately bright single stars); ``background_box_px``: SEP's
    background mesh; ``max_stars``: keep the brightest N per image (None: all); ``method``: ``psf-fit`` (default) or
    ``window`` (:data:`CENTROID_METHODS`); ``keep_saturated`` (default True): keep saturated stars (the brightest stars
    of a frame, the anchors of every pattern matcher: an 8-bit camera saturates its brightest stars in most exposures)
    with a windowed centroid (a clipped core does not follow the PSF), ranked first, flagged in the ``saturated`` column
    with a ``sigma_px`` of at least :data:`SATURATED_SIGMA_PX`, counted in ``FrameReport.saturated_kept``; False rejects
    them; ``footprint_follows_psf`` (default True): on a frame whose measured PSF is undersampled, detections of 1
    filtered pixel at a raised threshold are kept beside those of ``min_area_px`` when that is SEP's 2
    (:func:`hostlink.images.centroid.screen._footprint_px`); False: ``min_area_px`` on every frame."""

    threshold_sigma: float = 5.0
    min_area_px: int = _DEFAULT_MIN_AREA_PX
    dark: str | Path | None = None
    median: str | Path | None = None
    median_of_inputs: bool = False
    saturation_adu: float | None = None
    psf_sigma_px: float | None = None
    hot_pixel_chi2: float = 25.0
    max_ellipticity: float = 0.1
    keep_saturated: bool = True
    gain_e_per_adu: float | None = None
    method: str = "psf-fit"
    background_box_px: int = 64
    max_stars: int | None = None
    candidate_sigma: float | None = DEFAULT_CANDIDATE_SIGMA
    footprint_follows_psf: bool = True


@dataclass(frozen=True)
class TimeOptions:
    """Where the time of each image comes from (at most one; none: the files' metadata). ``time_utc``: one ISO UTC
    time for every image; ``times_file``: a text file, one line per image, ``NAME,TIME`` or ``NAME TIME`` (NAME the
    image's file name, TIME ISO UTC; ``#`` starts a comment); ``time_pattern``: a ``datetime.strptime`` pattern
    matching the whole file name or its stem (UTC unless it has ``%z``); ``date``: ``YYYY-MM-DD``, the UTC date with
    the time of day unknown (12:00:00 UTC is written: within 12 h of any time of that day, which moves annual
    aberration by at most 0.18", docs/file-formats.md); ``time_unknown``: no time (every ``t_utc`` empty)."""

    time_utc: str | None = None
    times_file: str | Path | None = None
    time_pattern: str | None = None
    date: str | None = None
    time_unknown: bool = False


@dataclass
class FrameReport:
    """What happened to one image: detections, the stars kept and every rejection by reason (``rejected_no_flux``: a
    detection whose PSF-fit flux is not positive, noise), the background noise [ADU], the PSF sigma used [px], the time
    and its source."""

    path: str
    detected: int = 0
    kept: int = 0
    rejected_hot: int = 0
    rejected_saturated: int = 0
    saturated_kept: int = 0
    rejected_blended: int = 0
    blended_kept: int = 0
    rejected_edge: int = 0
    rejected_no_flux: int = 0
    candidates: int = 0
    background_rms_adu: float = float("nan")
    psf_sigma_px: float = float("nan")
    time_utc: str = ""
    time_source: str = ""


@dataclass
class Detections:
    """The stars kept in one image, brightest first: centroid [px] (camera convention), flux [ADU], instrumental
    magnitude; ``report`` the counts; ``sigma_px`` each centroid's 1-sigma noise per axis [px]
    (:func:`centroid_sigma_px`); ``saturated`` True for a kept saturated star; ``blended`` True for a kept blend;
    ``blend_px`` the bias bound [px] from an elongated star's unresolved companion, in ``sigma_px`` as b / sqrt(2)
    per axis (NaN for a star not elongated; None: not stated)."""

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    mag: np.ndarray
    report: FrameReport = field(default_factory=lambda: FrameReport(path=""))
    sigma_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    saturated: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    candidates: Candidates | None = None
    blended: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    blend_px: np.ndarray | None = None


@dataclass(frozen=True)
class Candidates:
    """Faint candidates of one image (package docstring, step 7), most significant first: centroid [px], PSF-fit flux
    [ADU], instrumental magnitude, ``sigma_px`` and ``snr`` (the PSF-fit flux over its noise)."""

    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    mag: np.ndarray
    sigma_px: np.ndarray
    snr: np.ndarray


@dataclass
class CentroidResult:
    """The session (one frame per image, in time order; ``star_id`` 0; extra columns ``flux_adu``, ``sigma_px`` (each
    centroid's 1-sigma noise per axis [px], :func:`centroid_sigma_px`), ``saturated`` (1 for a kept saturated star),
    ``image``, ``time_source``) and one :class:`FrameReport` per frame."""

    session: Session
    frames: list[FrameReport]


def _check_options(options: CentroidOptions) -> None:
    if not (math.isfinite(options.threshold_sigma) and options.threshold_sigma > 0):
        raise UserError(f"threshold-sigma must be a number > 0, got {options.threshold_sigma!r}")
    if options.min_area_px < 1:
        raise UserError(f"minimum area must be >= 1 px, got {options.min_area_px}")
    if options.psf_sigma_px is not None and not (options.psf_sigma_px > 0):
        raise UserError(f"psf sigma must be > 0 px, got {options.psf_sigma_px!r}")
    if options.gain_e_per_adu is not None and not (options.gain_e_per_adu > 0):
        raise UserError(f"gain must be > 0 e-/ADU, got {options.gain_e_per_adu!r}")
    if options.method not in CENTROID_METHODS:
        raise UserError(f"centroid method must be one of {', '.join(CENTROID_METHODS)}, got {options.method!r}")
    if options.candidate_sigma is not None and not (
        math.isfinite(options.candidate_sigma) and options.candidate_sigma > 0
    ):
        raise UserError(f"candidate-sigma must be a number > 0, got {options.candidate_sigma!r}")
    if options.max_stars is not None and options.max_stars < 1:
        raise UserError(f"max-stars must be >= 1, got {options.max_stars}")
