"""The time of each image: an option, a times file, a pattern on the file name, a date, or the file's metadata
(:mod:`hostlink.images.centroid`)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from hostlink.errors import UserError, one_line
from hostlink.files.times import parse_iso_utc_many
from hostlink.images.centroid.options import TimeOptions
from hostlink.images.read import RawImage


def _time_choices(times: TimeOptions) -> dict[str, bool]:
    return {
        "--time": times.time_utc is not None,
        "--times": times.times_file is not None,
        "--time-pattern": times.time_pattern is not None,
        "--date": times.date is not None,
        "--time-unknown": bool(times.time_unknown),
    }


def image_time(image: RawImage, times: TimeOptions, listed: dict[str, str] | None = None) -> tuple[str, str]:
    """(ISO UTC time or "" when unknown, its source) of one image: the option given, else the file's metadata; no
    time at all is a one-line UserError naming the image."""
    name = image.path.name
    if times.time_unknown:
        return "", "unknown"
    if times.time_utc is not None:
        return _checked_iso(times.time_utc, "--time"), "option"
    if listed is not None:
        if name not in listed:
            raise UserError(f"{image.path}: not listed in the times file {times.times_file}")
        return listed[name], f"times file {Path(str(times.times_file)).name}"
    if times.time_pattern is not None:
        return _time_from_name(image.path, times.time_pattern), f"file name ({times.time_pattern})"
    if times.date is not None:
        return _date_noon(times.date), "date only (time of day unknown: 12:00 UTC)"
    if image.time_utc is not None:
        return image.time_utc, str(image.time_source)
    raise UserError(
        f"{image.path}: no time known (no FITS DATE-OBS / EXIF DateTimeOriginal): give --time, --times FILE, "
        "--time-pattern, --date or --time-unknown"
    )


def _checked_iso(text: str, what: str) -> str:
    try:
        parse_iso_utc_many([text])
    except ValueError as exc:
        raise UserError(f"{what}: {exc}") from None
    return str(text).strip()


def _date_noon(text: str) -> str:
    try:
        day = _dt.date.fromisoformat(str(text).strip())
    except ValueError:
        raise UserError(f"--date: not a date YYYY-MM-DD: {text!r}") from None
    return f"{day.isoformat()}T12:00:00.000Z"


def _time_from_name(path: Path, pattern: str) -> str:
    last: Exception | None = None
    for candidate in (path.name, path.stem):
        try:
            when = _dt.datetime.strptime(candidate, pattern)
            break
        except ValueError as exc:
            last = exc
    else:
        raise UserError(f"{path}: the file name does not match --time-pattern {pattern!r} ({one_line(last)})")
    if when.tzinfo is not None:
        when = when.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def _read_times_file(path: Path) -> dict[str, str]:
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read ({one_line(exc)})") from None
    out: dict[str, str] = {}
    for k, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p.strip() for p in (text.split(",") if "," in text else text.split(None, 1))]
        if len(parts) != 2 or not parts[0] or not parts[1]:
            raise UserError(f"{path}: line {k}: expected 'IMAGE_NAME,ISO_UTC_TIME', got {line.strip()!r}")
        out[Path(parts[0]).name] = _checked_iso(parts[1], f"{path}: line {k}")
    return out
