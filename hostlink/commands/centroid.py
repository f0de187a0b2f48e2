"""``hostlink centroid``: star centroids from images into a session (issue 11).

Parses the options, calls :func:`hostlink.images.centroid.centroid_images` (the method and its checks are there),
writes the session through the one session writer and prints one line per image.
"""

from __future__ import annotations

import argparse

HELP = "find star centroids in images (FITS, TIFF, PNG, JPEG) and write them as a session of unidentified stars"
DESCRIPTION = (
    "Read each IMAGE (FITS, 8/16-bit TIFF, 8/16-bit grey or RGB PNG, JPEG; a colour image as the mean of its "
    "channels), subtract a dark or median frame if given, then a local background (SEP), detect stars (SEP's "
    "matched filter and deblending), reject hot pixels (a single bright pixel that fits better than a star of the "
    "frame's measured PSF), keep blended stars (deblended beside a neighbour, or elongated: an unresolved pair) "
    "flagged with the bound on their bias in sigma_px (rejected when it exceeds 2 px), centroid stars cut by the "
    "image edge on the pixels they have, keep saturated stars (flagged; --reject-saturated drops them), and "
    "centroid the rest by "
    "fitting the pixel-integrated Gaussian PSF of the frame's width, started at SEP's windowed centroid. Writes "
    "SESSION.csv: one frame per image in time order, star_id 0, x_px/y_px with (0, 0) the centre of the top-left "
    "pixel, mag the instrumental magnitude (-2.5 log10 flux), extra columns flux_adu, sigma_px (the centroid's "
    "1-sigma noise per axis, its Cramer-Rao bound from flux, noise and PSF), saturated, blended, image, "
    "image_width_px and image_height_px (its size: identify and calibrate refuse a nominal of another "
    "image_size_px) and time_source. The "
    "time of each image comes from one option (--time, --times, --time-pattern, --date, --time-unknown) or else from "
    "the file (FITS DATE-AVG or DATE-OBS + EXPTIME/2; EXIF DateTimeOriginal); an image with no known time is an "
    "error, and so is an image of another size than the first (a session is one camera's) or a file given twice. "
    "Exit 2 when no star is found in any image. After each frame's stars come its fainter candidates "
    "(--candidate-sigma, default 3: local maxima of the filtered image outside every detection whose PSF-fit flux "
    "is at least that many times its noise), flagged by their significance in an snr column: identify builds no "
    "pattern from them and names one only where the calibrated camera predicts a catalogue star."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "images", nargs="+", metavar="IMAGE", help="image files (.fits/.fit, .tif/.tiff, .png, .jpg/.jpeg)"
    )
    parser.add_argument("--out", required=True, metavar="SESSION.csv", help="session file to write")
    _add_background_arguments(parser)
    _add_time_arguments(parser)
    _add_detection_arguments(parser)
    _add_candidate_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")


def _add_background_arguments(parser: argparse.ArgumentParser) -> None:
    """The background subtracted: a dark frame, a median of frames, or the median of the inputs."""
    background = parser.add_mutually_exclusive_group()
    background.add_argument("--dark", metavar="FILE", help="dark frame to subtract from every image first")
    background.add_argument("--median", metavar="FILE", help="median (sky) frame to subtract from every image first")
    background.add_argument(
        "--median-of-inputs",
        action="store_true",
        help="subtract the per-pixel median of the IMAGEs themselves (>= 3 images at different pointings)",
    )


def _add_time_arguments(parser: argparse.ArgumentParser) -> None:
    """When each image was taken: one time, a file of times, a pattern in the names, a date, or unknown."""
    when = parser.add_mutually_exclusive_group()
    when.add_argument("--time", metavar="ISO", help="exposure mid-time of every image, ISO 8601 UTC")
    when.add_argument(
        "--times", metavar="FILE", help="text file, one line per image: FILE_NAME,ISO_UTC_TIME (# comments)"
    )
    when.add_argument(
        "--time-pattern",
        metavar="STRPTIME",
        help="read the time from each file name, e.g. 'img_%%Y%%m%%d_%%H%%M%%S' (UTC unless the pattern has %%z)",
    )
    when.add_argument(
        "--date",
        metavar="YYYY-MM-DD",
        help="UTC date only, time of day unknown: writes 12:00:00 UTC (annual aberration then errs <= 0.18 arcsec)",
    )
    when.add_argument(
        "--time-unknown", action="store_true", help="no time: t_utc empty (calibrate then uses J2000 directions)"
    )


def _add_detection_arguments(parser: argparse.ArgumentParser) -> None:
    """How stars are found and measured: threshold, area, saturation, PSF width, gain, centroid method, count."""
    parser.add_argument(
        "--threshold-sigma",
        type=float,
        default=5.0,
        metavar="N",
        help="detection threshold in units of the local background noise (default 5)",
    )
    parser.add_argument(
        "--min-area",
        type=int,
        default=2,
        metavar="PX",
        help="minimum footprint in pixels above the threshold (default 2: a sharp faint star has 1-2)",
    )
    parser.add_argument(
        "--saturation-adu",
        type=float,
        metavar="ADU",
        help="level at which the detector clips (default: the file type's maximum, or FITS SATURATE)",
    )
    saturated = parser.add_mutually_exclusive_group()
    saturated.add_argument(
        "--keep-saturated",
        action="store_true",
        help="keep saturated stars (the default): windowed centroid, ranked first, flagged in the saturated column",
    )
    saturated.add_argument(
        "--reject-saturated", action="store_true", help="reject saturated stars instead of keeping them"
    )
    parser.add_argument(
        "--psf-sigma-px", type=float, metavar="PX", help="PSF sigma for the centroid window (default: measured)"
    )
    parser.add_argument(
        "--gain",
        type=float,
        metavar="E_PER_ADU",
        help="detector gain [e-/ADU], if known: the PSF fit and the blend test then weigh the stars' shot noise",
    )
    parser.add_argument(
        "--centroid",
        choices=("psf-fit", "window"),
        default="psf-fit",
        help="psf-fit: fit the pixel-integrated Gaussian PSF, maximum likelihood (default); window: SEP's windowed "
        "centroid only",
    )
    parser.add_argument("--max-stars", type=int, metavar="N", help="keep only the N brightest stars of each image")


def _add_candidate_arguments(parser: argparse.ArgumentParser) -> None:
    """The faint candidates kept beside the stars, or none."""
    candidates = parser.add_mutually_exclusive_group()
    candidates.add_argument(
        "--candidate-sigma",
        type=float,
        default=3.0,
        metavar="N",
        help="also write fainter candidates down to this significance, flagged in the snr column (default 3; none "
        "when not below --threshold-sigma): identify names one only where the calibrated camera predicts a catalogue "
        "star",
    )
    candidates.add_argument("--no-candidates", action="store_true", help="write the detected stars only")


def run(args: argparse.Namespace) -> int:
    from hostlink.api import CentroidOptions, TimeOptions, centroid_images, progress_bar, write_session

    options = CentroidOptions(
        threshold_sigma=args.threshold_sigma,
        min_area_px=args.min_area,
        dark=args.dark,
        median=args.median,
        median_of_inputs=args.median_of_inputs,
        saturation_adu=args.saturation_adu,
        psf_sigma_px=args.psf_sigma_px,
        gain_e_per_adu=args.gain,
        method=args.centroid,
        keep_saturated=not args.reject_saturated,
        max_stars=args.max_stars,
        candidate_sigma=None if args.no_candidates else args.candidate_sigma,
    )
    times = TimeOptions(
        time_utc=args.time,
        times_file=args.times,
        time_pattern=args.time_pattern,
        date=args.date,
        time_unknown=args.time_unknown,
    )
    with progress_bar("centroiding images", len(args.images), enabled=not args.quiet) as advance:
        result = centroid_images(args.images, options, times, progress=advance)
    write_session(args.out, result.session)
    if not args.quiet:
        for k, f in enumerate(result.frames):
            print(
                f"frame {k} {f.path}: {f.kept} stars of {f.detected} detections (rejected: {f.rejected_hot} hot, "
                f"{f.rejected_saturated} saturated, {f.rejected_blended} blended, {f.rejected_edge} at the edge, "
                f"{f.rejected_no_flux} without flux"
                f"; {f.saturated_kept} saturated kept, {f.blended_kept} blends kept flagged); "
                f"noise {f.background_rms_adu:.2f} ADU, PSF sigma {f.psf_sigma_px:.2f} px; "
                f"{_time_text(f.time_utc, f.time_source)}; {f.candidates} fainter candidates"
            )
        held = sum(f.candidates for f in result.frames)
        print(
            f"{held} fainter candidates and {len(result.session) - held} stars in {len(result.frames)} images; "
            f"wrote {args.out}"
        )
    return 0


def _time_text(time_utc: str, time_source: str) -> str:
    """A frame's time and where it came from, for the frame's line; with no time (``--time-unknown``) only that."""
    return f"time {time_utc} ({time_source})" if time_utc else "time unknown"
