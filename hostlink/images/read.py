"""THE image reader of the host (docs/architecture.md ``hostlink/images``): FITS (astropy.io.fits), TIFF 8/16 bit
(tifffile) and PNG/JPEG (Pillow), each into one float64 array of detector counts [ADU] plus what the file says about
the exposure (its time, its saturation level).

Pixel layout: ``pixels[row, column]``, row 0 first in the file, so the pixel centre ``(x, y) = (column, row)`` is the
camera-model convention (docs/camera-model.md: ``(0, 0)`` is the centre of the first, top-left pixel). A FITS image
is stored bottom row first by convention but is read exactly as stored (array row 0 = first row in the file, which
is what FITS viewers show at the bottom): the centroids then belong to the stored array, as a sensor reading out
the same detector would give them. A colour image (RGB or RGBA) is read as the mean of its three colour channels
(alpha ignored): a star tracker's centroid uses the light of every channel.

Time (exposure mid-time, UTC, ISO 8601 as the session file writes it):
- FITS: ``DATE-AVG`` (mid-exposure, FITS standard 4.0 sec. 9.4), else ``DATE-OBS`` (start) + ``EXPTIME`` / 2
  (``DATE-OBS`` alone when there is no ``EXPTIME``, said so in ``time_source``); a date-only ``DATE-OBS`` with the
  old ``TIME-OBS`` (or ``UT``) keyword is joined. ``TIMESYS`` other than UTC (TT, TAI, GPS) is converted by
  :func:`hostlink.files.times.iso_to_utc` (ERFA).
- EXIF (PNG ``eXIf`` or TIFF EXIF IFD): ``DateTimeOriginal`` (start of exposure) + ``SubSecTimeOriginal``, shifted by
  ``OffsetTimeOriginal`` to UTC, + ``ExposureTime`` / 2. Without an offset the camera clock is read as UTC, and
  ``time_source`` says so.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostlink.errors import UserError, one_line
from hostlink.files.times import iso_plus_seconds, iso_to_utc

#: File suffixes of each reader (lower case).
FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")
TIFF_SUFFIXES = (".tif", ".tiff")
PILLOW_SUFFIXES = (".png", ".jpg", ".jpeg")

# EXIF tag numbers (EXIF 2.32, CIPA DC-008-2019, table 7 and 9)
_EXIF_IFD = 0x8769
_DATETIME_ORIGINAL = 0x9003
_OFFSET_TIME_ORIGINAL = 0x9011
_SUBSEC_TIME_ORIGINAL = 0x9291
_EXPOSURE_TIME = 0x829A


@dataclass(frozen=True)
class RawImage:
    """One image as read: ``pixels`` (height, width) float64 [ADU]; ``saturation_adu`` the level at which the detector
    or its file clips (FITS ``SATURATE`` or ``DATAMAX``, else the integer type's maximum, for FITS scaled by
    ``BZERO``/``BSCALE``; None when unknown, e.g. float data);
    ``time_utc`` the exposure mid-time from the file's metadata (None when it gives none) and ``time_source`` where
    it came from."""

    path: Path
    pixels: np.ndarray
    saturation_adu: float | None
    time_utc: str | None = None
    time_source: str | None = None

    @property
    def image_size_px(self) -> tuple[int, int]:
        """(width, height) [px], as parameter files give ``image_size_px``."""
        return int(self.pixels.shape[1]), int(self.pixels.shape[0])


def image_kind(path: Path) -> str:
    """``fits``, ``tiff`` or ``pillow`` from the file name's suffix; an unknown suffix is a one-line UserError."""
    name = path.name.lower()
    for kind, suffixes in (("fits", FITS_SUFFIXES), ("tiff", TIFF_SUFFIXES), ("pillow", PILLOW_SUFFIXES)):
        if name.endswith(suffixes):
            return kind
    known = ", ".join(FITS_SUFFIXES + TIFF_SUFFIXES + PILLOW_SUFFIXES)
    raise UserError(f"{path}: unknown image type (known suffixes: {known})")


def read_image(path: str | Path) -> RawImage:
    """Read one image file (FITS, TIFF, PNG, JPEG; by suffix) into a :class:`RawImage`. A missing, truncated or
    undecodable file, or one that is not a single 2-D (or colour) image, is a one-line :class:`UserError`."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a directory, not an image (give its images, e.g. {path}/*.fits)")
    kind = image_kind(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    reader = {"fits": _read_fits, "tiff": _read_tiff, "pillow": _read_pillow}[kind]
    try:
        pixels, saturation, time_utc, source = reader(path)
    except UserError:
        raise
    except Exception as exc:  # any decoder's failure on a damaged file becomes one line naming the file
        raise UserError(f"{path}: cannot read the image ({one_line(exc)})") from None
    pixels = _to_grey(path, pixels)
    if pixels.shape[0] < 8 or pixels.shape[1] < 8:
        raise UserError(f"{path}: image of {pixels.shape[1]} x {pixels.shape[0]} px is too small to hold a star")
    if not np.all(np.isfinite(pixels)):
        raise UserError(f"{path}: {int(np.sum(~np.isfinite(pixels)))} pixel(s) are not finite (NaN or inf)")
    return RawImage(path, pixels, saturation, time_utc, source)


def _to_grey(path: Path, pixels: np.ndarray) -> np.ndarray:
    data = np.asarray(pixels)
    if data.ndim == 3 and data.shape[-1] in (3, 4):
        data = _mean_of_three(data[..., 0], data[..., 1], data[..., 2])
    elif data.ndim == 3 and data.shape[0] in (3, 4) and data.shape[-1] > 4:  # planar colour
        data = _mean_of_three(data[0], data[1], data[2])
    if data.ndim != 2:
        raise UserError(f"{path}: not a single image (array shape {tuple(np.shape(pixels))})")
    return np.ascontiguousarray(data, dtype=np.float64)


def _mean_of_three(red: np.ndarray, green: np.ndarray, blue: np.ndarray) -> np.ndarray:
    """The grey level of a colour image, (r + g + b) / 3 in float64: the same sums in the same order as numpy's mean
    over a colour axis (three terms, summed one after the other, then divided: bit for bit its result), without its
    slow reduction over a short strided axis."""
    grey = red.astype(np.float64)
    grey += green
    grey += blue
    grey /= 3.0
    return grey


def _integer_max(dtype: np.dtype) -> float | None:
    return float(np.iinfo(dtype).max) if np.issubdtype(dtype, np.integer) else None


# ----------------------------------------------------------------------------------------------------------------
# FITS


#: FITS files are made of blocks of this many bytes (FITS 4.0 sec. 3.1).
FITS_BLOCK_BYTES = 2880


def _read_fits(path: Path):
    """A FITS image; astropy's warnings on a damaged file are collected, not printed, and a failure is one line
    that names what is wrong with the file (never astropy's advice to pass it an option: hostlink has none)."""
    import warnings

    from astropy.io import fits  # noqa: F401 - imported first: astropy's import installs its own warning logger

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            return _read_fits_checked(path)
        except UserError:
            raise
        except Exception as exc:  # noqa: BLE001 - astropy on a user's file: one line, never a traceback
            raise UserError(f"{path}: {_fits_problem(path, exc, caught)}") from None


def _fits_problem(path: Path, exc: BaseException, caught: list) -> str:
    """What is wrong with a FITS file astropy could not read, in words about the file."""
    first = one_line(exc).split(". ")[0]  # astropy appends advice ("try with ignore_missing_...=True") after a stop
    size = path.stat().st_size
    if size == 0:
        return "empty file, not a FITS image"
    if path.name.lower().endswith(".gz"):  # compressed: its bytes say nothing of the FITS inside
        return f"cannot read the compressed FITS image ({first})"
    with path.open("rb") as fh:
        start = fh.read(30)
    if not start.startswith(b"SIMPLE  ="):
        return "not a FITS file (a FITS file starts with the card SIMPLE = T)"
    texts = " ".join(str(w.message) for w in caught)
    expected = re.search(r"expected size \((\d+)\)", texts)
    if expected:
        return (
            f"truncated FITS file: {size} bytes where its header describes {expected.group(1)}; copy it again from "
            "its source"
        )
    if size % FITS_BLOCK_BYTES:
        return (
            f"truncated or damaged FITS file: {size} bytes, not a whole number of {FITS_BLOCK_BYTES}-byte blocks; "
            "copy it again from its source"
        )
    if "END card" in first:
        return "damaged FITS header: it has no END card (the file was cut or overwritten)"
    return f"cannot read the FITS image ({first})"


def _read_fits_checked(path: Path):
    from astropy.io import fits

    with fits.open(path, memmap=False) as hdus:
        hdu = next((h for h in hdus if getattr(h, "data", None) is not None and h.data.ndim >= 2), None)
        if hdu is None:
            raise UserError(f"{path}: no image in the FITS file")
        header = hdu.header
        pixels = np.array(hdu.data, dtype=np.float64)
        saturation = header.get("SATURATE", header.get("DATAMAX"))
        bitpix = int(header.get("BITPIX", -32))
        if saturation is None and bitpix > 0:  # integer data: the stored type's maximum, scaled (FITS 4.0 sec. 4.4.2.5)
            stored_max = 255 if bitpix == 8 else 2 ** (bitpix - 1) - 1
            saturation = float(header.get("BZERO", 0.0)) + float(header.get("BSCALE", 1.0)) * stored_max
        time_utc, source = _fits_time(path, header)
    return pixels, None if saturation is None else float(saturation), time_utc, source


def _fits_time(path: Path, header) -> tuple[str | None, str | None]:
    scale = str(header.get("TIMESYS", "UTC")).strip().upper()
    if "DATE-AVG" in header:
        text, shift_s, source = str(header["DATE-AVG"]).strip(), 0.0, "FITS DATE-AVG"
    elif "DATE-OBS" in header:
        text = str(header["DATE-OBS"]).strip()
        if "T" not in text and ("TIME-OBS" in header or "UT" in header):
            text = f"{text}T{str(header.get('TIME-OBS', header.get('UT'))).strip()}"
        exposure = header.get("EXPTIME", header.get("EXPOSURE"))
        if exposure is None:
            shift_s, source = 0.0, "FITS DATE-OBS (start of exposure: no EXPTIME)"
        else:
            shift_s, source = 0.5 * float(exposure), "FITS DATE-OBS + EXPTIME/2"
    else:
        return None, None
    if scale != "UTC":
        source += f" (TIMESYS {scale})"
    try:
        return iso_plus_seconds(iso_to_utc(text, scale), shift_s), source
    except ValueError as exc:
        raise UserError(f"{path}: FITS time {text!r} (TIMESYS {scale}) is not readable ({one_line(exc)})") from None


def _iso_z(when: _dt.datetime) -> str:
    """A naive-UTC datetime as the session file's ISO form with milliseconds and ``Z``."""
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


# ----------------------------------------------------------------------------------------------------------------
# TIFF and Pillow formats (EXIF)


def _read_tiff(path: Path):
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        pixels = tif.series[0].asarray()  # all pages of the first series: a stack of frames is refused below
        exif = {}
        tags = page.tags
        if "ExifTag" in tags and isinstance(tags["ExifTag"].value, dict):
            exif = {_EXIF_NAMES.get(k, k): v for k, v in tags["ExifTag"].value.items()}
    time_utc, source = _exif_time(path, exif)
    return pixels, _integer_max(pixels.dtype), time_utc, source


#: tifffile names the EXIF fields; Pillow numbers them: both are looked up by name here.
_EXIF_NAMES = {
    _DATETIME_ORIGINAL: "DateTimeOriginal",
    _OFFSET_TIME_ORIGINAL: "OffsetTimeOriginal",
    _SUBSEC_TIME_ORIGINAL: "SubsecTimeOriginal",
    _EXPOSURE_TIME: "ExposureTime",
}


def _read_pillow(path: Path):
    from PIL import Image

    with Image.open(path) as im:
        im.load()
        mode = im.mode
        file_format = im.format
        if mode in ("P", "1", "LA", "PA", "CMYK", "YCbCr", "LAB", "HSV"):
            im = im.convert("RGB" if mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV") else "L")
        pixels = np.asarray(im)
        exif_ifd = im.getexif().get_ifd(_EXIF_IFD)
        exif = {_EXIF_NAMES.get(k, k): v for k, v in exif_ifd.items()}
    if file_format == "PNG" and mode in ("I", "I;16", "I;16B"):
        # PNG stores at most 16 bits per sample; Pillow < 10.1 opens 16-bit greyscale as 32-bit mode "I"
        saturation = 65535.0
    elif mode in ("I", "F"):  # 32-bit int or float images: the level they clip at is not in the file
        saturation = None
    elif pixels.dtype == np.int32 and mode.startswith("I;16"):
        saturation = 65535.0
    else:
        saturation = _integer_max(pixels.dtype)
    time_utc, source = _exif_time(path, exif)
    return pixels, saturation, time_utc, source


_EXIF_DATETIME = re.compile(r"^(\d{4}):(\d{2}):(\d{2}) (\d{2}):(\d{2}):(\d{2})$")
_EXIF_OFFSET = re.compile(r"^([+-])(\d{2}):(\d{2})$")


def _exif_time(path: Path, exif: dict) -> tuple[str | None, str | None]:
    """EXIF DateTimeOriginal (+ SubSecTimeOriginal, - OffsetTimeOriginal, + ExposureTime / 2) as ISO UTC."""
    text = exif.get("DateTimeOriginal")
    if text is None:
        return None, None
    m = _EXIF_DATETIME.match(str(text).strip("\x00 "))
    if not m:
        raise UserError(f"{path}: EXIF DateTimeOriginal {text!r} is not 'YYYY:MM:DD hh:mm:ss'")
    try:
        when = _dt.datetime(*(int(g) for g in m.groups()))
    except ValueError as exc:
        raise UserError(f"{path}: EXIF DateTimeOriginal {text!r}: {exc}") from None
    subsec = str(exif.get("SubsecTimeOriginal", "") or "").strip("\x00 ")
    if subsec.isdigit():
        when += _dt.timedelta(seconds=float("0." + subsec))
    source = "EXIF DateTimeOriginal"
    offset = str(exif.get("OffsetTimeOriginal", "") or "").strip("\x00 ")
    m_off = _EXIF_OFFSET.match(offset)
    if m_off:
        sign = 1 if m_off.group(1) == "+" else -1
        when -= sign * _dt.timedelta(hours=int(m_off.group(2)), minutes=int(m_off.group(3)))
    else:
        source += " (no OffsetTimeOriginal: camera clock read as UTC)"
    exposure = exif.get("ExposureTime")
    exposure_s = _rational(exposure)
    if exposure_s is not None:
        when += _dt.timedelta(seconds=0.5 * exposure_s)
        source += " + ExposureTime/2"
    return _iso_z(when), source


def _rational(value) -> float | None:
    if value is None:
        return None
    try:
        if isinstance(value, tuple) and len(value) == 2:  # tifffile gives (numerator, denominator)
            out = float(value[0]) / float(value[1])
        else:
            out = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return out if math.isfinite(out) and out >= 0 else None
