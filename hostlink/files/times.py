"""THE time module of the host (docs/architecture.md: hostlink/files): every ISO 8601 time stamp is parsed and written
here, and UTC is converted to TT / UT1 here (pyerfa).

Three forms of a UTC time:
- the session file's ISO 8601 string, ``2026-03-14T02:10:00.125Z`` (docs/file-formats.md: ``T`` or a space; ``Z``,
  ``+00:00`` or nothing after it; any number of decimals);
- two-part Julian dates (jd1, jd2) as ERFA takes them (``dtf2d`` with scale "UTC": leap seconds handled), which keep
  sub-microsecond resolution, for astrometry;
- the wire's int64 microseconds since 1970-01-01T00:00:00 UTC, leap seconds not counted (POSIX time,
  ``protocol.messages``), in integer arithmetic, so a time with up to 6 decimals of a second survives the round trip
  exactly. A leap second (second 60.x) maps onto the next minute.
"""

from __future__ import annotations

import calendar
import re
from collections.abc import Iterable

import erfa
import numpy as np

_ISO = re.compile(r"^(\d{4})-(\d{2})-(\d{2})[T ](\d{2}):(\d{2}):(\d{2})(?:\.(\d+))?(Z|[+-]00:?00)?$")
_US_PER_S = 1_000_000
#: The years a time stamp may fall in. From 1960: UTC is defined from then on (before it ERFA's dtf2d and dat call the
#: year "dubious" and have no TAI - UTC). Through 2100: ERFA's Earth ephemeris (epv00, which apci13 uses for the
#: aberration of every reference direction) is fitted to 1900-2100 and holds its stated accuracy only there. A date
#: outside is a one-line refusal, not ERFA's "dubious year" warning and a result computed anyway (a fuzzed session
#: dated 9999 was read that way). Within the span, a date past ERFA's leap-second table still warns "dubious year":
#: leap seconds not yet announced are unknown, which moves TT by seconds (under 1e-5 arcsec in a reference direction).
YEARS = (1960, 2100)


def _iso_match(text: str) -> re.Match:
    m = _ISO.match(str(text).strip())
    if not m:
        raise ValueError(f"not an ISO 8601 UTC time: {text!r} (expected e.g. 2026-03-14T02:10:00.000Z)")
    return m


def parse_iso_utc(text: str) -> tuple[int, int, int, int, int, float]:
    """Parse ``YYYY-MM-DDThh:mm:ss[.fff][Z]`` (UTC) into (year, month, day, hour, minute, seconds); raises
    ValueError with the offending text (a year outside :data:`YEARS` too)."""
    m = _iso_match(text)
    y, mo, d, h, mi = (int(m.group(k)) for k in range(1, 6))
    _check_year(y, text)
    return y, mo, d, h, mi, float(f"{m.group(6)}.{m.group(7) or '0'}")


def _check_year(year: int, text: str) -> None:
    """ValueError naming ``text`` when ``year`` is outside :data:`YEARS`."""
    if not YEARS[0] <= year <= YEARS[1]:
        raise ValueError(
            f"{text!r}: year {year} is outside {YEARS[0]}..{YEARS[1]} (UTC is defined from {YEARS[0]}; ERFA's Earth "
            f"ephemeris holds its accuracy to {YEARS[1]})"
        )


#: From this many time stamps on, :func:`parse_iso_utc_many` parses them in one pass of pyarrow's RE2 (the same
#: pattern as :data:`_ISO`) instead of one Python regex match each: a large session is read faster (measured in
#: docs/file-formats.md, "Large sessions").
VECTOR_PARSE_FROM = 64


def parse_iso_utc_many(texts: Iterable[str]) -> tuple[np.ndarray, np.ndarray]:
    """ISO strings -> UTC quasi Julian dates (jd1, jd2) as ERFA expects them (dtf2d, scale "UTC"). The same fields
    as :func:`parse_iso_utc` of each (a text it refuses, a year outside :data:`YEARS` too, is its ValueError)."""
    texts = list(texts)
    if not texts:
        return np.zeros(0), np.zeros(0)
    if len(texts) >= VECTOR_PARSE_FROM:
        arr = _iso_fields_vectorised(texts)
        outside = (arr[:, 0] < YEARS[0]) | (arr[:, 0] > YEARS[1])
        if outside.any():
            k = int(np.argmax(outside))
            _check_year(int(arr[k, 0]), texts[k])
    else:
        arr = np.array([parse_iso_utc(t) for t in texts], dtype=np.float64)
    try:
        jd1, jd2 = erfa.dtf2d(
            "UTC",
            arr[:, 0].astype(int),
            arr[:, 1].astype(int),
            arr[:, 2].astype(int),
            arr[:, 3].astype(int),
            arr[:, 4].astype(int),
            arr[:, 5],
        )
    except (erfa.ErfaError, ValueError) as exc:
        raise ValueError(f"invalid date or time ({exc})") from None
    return np.atleast_1d(jd1), np.atleast_1d(jd2)


def _iso_fields_vectorised(texts: list) -> np.ndarray:
    """(n, 6) float64 fields (year, month, day, hour, minute, seconds) of ``texts``, as :func:`parse_iso_utc` gives
    them: matched by pyarrow (RE2, ASCII digits) in one pass; a text it does not match (another kind of digit, or
    not a time) goes through :func:`parse_iso_utc`, which parses or refuses it."""
    import pyarrow as pa
    import pyarrow.compute as pc

    pattern = _ISO.pattern
    for name in ("y", "mo", "d", "h", "mi", "s", "frac"):  # RE2 extracts named groups only
        pattern = pattern.replace("(\\d", f"(?P<{name}>\\d", 1)
    pattern = pattern.replace("(Z|", "(?:Z|")  # the zone: matched, not extracted
    cells = pc.ascii_trim_whitespace(pa.array([str(t) for t in texts], type=pa.string()))
    unmatched = pc.invert(pc.match_substring_regex(cells, pattern)).to_numpy(zero_copy_only=False)
    if unmatched.any():  # parsed one at a time below; a valid stand-in keeps the columns' casts total
        cells = pc.if_else(pa.array(unmatched), "2000-01-01T00:00:00", cells)
    parts = pc.extract_regex(cells, pattern)
    fields = np.empty((len(texts), 6), dtype=np.float64)
    for k, name in enumerate(("y", "mo", "d", "h", "mi")):
        fields[:, k] = pc.cast(parts.field(name), pa.float64()).to_numpy(zero_copy_only=False)
    frac = parts.field("frac")  # "" when the time has no decimals
    seconds = pc.binary_join_element_wise(parts.field("s"), pc.if_else(pc.equal(frac, ""), "0", frac), ".")
    fields[:, 5] = pc.cast(seconds, pa.float64()).to_numpy(zero_copy_only=False)
    for k in np.flatnonzero(unmatched):
        fields[k] = parse_iso_utc(texts[k])
    return fields


def fixed_time_from_iso(text: str):
    """An ISO UTC time stamp -> ``onboard.timescale.FixedTime`` (UTC) from its calendar fields, as a sensor builds it
    (``from_calendar``, integer arithmetic). Not via ``dtf2d``: on a day with a leap second its quasi Julian date
    counts 86401 s, and reading that fraction as one of 86400 s puts the clock up to 1 s (15" of Earth rotation)
    behind."""
    from onboard.timescale import from_calendar

    y, mo, d, h, mi, s = parse_iso_utc(text)
    return from_calendar(y, mo, d, h, mi, round(s * _US_PER_S))


def tai_minus_utc_s(jd_utc1: float, jd_utc2: float) -> int:
    """Leap seconds TAI - UTC [s] at a UTC two-part Julian date (``erfa.dat``): the data a sensor is given with its
    time."""
    y, m, d, fd = erfa.jd2cal(jd_utc1, jd_utc2)
    return int(round(float(erfa.dat(y, m, d, fd))))


#: Time scales :func:`iso_to_utc` reads, with their offset [s] to the ERFA scale they are read in (GPS = TAI - 19 s).
TIME_SCALES = {"UTC": ("UTC", 0.0), "TAI": ("TAI", 0.0), "TT": ("TT", 0.0), "GPS": ("TAI", 19.0)}


def iso_to_utc(text: str, scale: str) -> str:
    """An ISO 8601 date-time in the time scale ``scale`` (UTC, TAI, TT or GPS: a FITS ``TIMESYS``) -> ISO UTC with
    milliseconds and a Z (ERFA dtf2d, tttai, taiutc, d2dtf: leap seconds applied). Raises ValueError naming the
    text or the scale."""
    key = str(scale).strip().upper()
    if key not in TIME_SCALES:
        raise ValueError(f"time scale {scale!r} is not one of {', '.join(TIME_SCALES)}")
    erfa_scale, plus_s = TIME_SCALES[key]
    y, mo, d, h, mi, sec = parse_iso_utc(text)
    try:
        jd1, jd2 = erfa.dtf2d(erfa_scale, y, mo, d, h, mi, sec)
        jd2 = jd2 + plus_s / 86400.0
        if erfa_scale == "TT":
            jd1, jd2 = erfa.tttai(jd1, jd2)
        if erfa_scale != "UTC":
            jd1, jd2 = erfa.taiutc(jd1, jd2)
        (yy, mm, dd, ihmsf) = erfa.d2dtf("UTC", 3, jd1, jd2)
    except (erfa.ErfaError, ValueError) as exc:
        raise ValueError(f"invalid date or time {text!r} ({exc})") from None
    hh, mn, ss, ms = (int(v) for v in np.asarray(ihmsf).tolist())
    return f"{int(yy):04d}-{int(mm):02d}-{int(dd):02d}T{hh:02d}:{mn:02d}:{ss:02d}.{ms:03d}Z"


def utc_to_tt(jd1: np.ndarray, jd2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UTC -> TT two-part Julian dates (ERFA utctai, taitt)."""
    tai1, tai2 = erfa.utctai(jd1, jd2)
    return erfa.taitt(tai1, tai2)


def utc_to_ut1(jd1: np.ndarray, jd2: np.ndarray, dut1_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """UTC -> UT1 with UT1 - UTC = dut1_s (docs/interfaces.md: 0 unless --dut1 is given)."""
    return erfa.utcut1(jd1, jd2, dut1_s)


# ------------------------------------------------------------------------------ wire time (POSIX microseconds)
def iso_to_t_us(text: str) -> int:
    """``2026-03-14T02:10:00.125Z`` -> microseconds since 1970 UTC, exact (decimals beyond the 6th are dropped; a
    leap second 60.x maps onto the next minute)."""
    m = _iso_match(text)
    y, mo, d, h, mi = (int(m.group(k)) for k in range(1, 6))
    frac_us = int(((m.group(7) or "") + "000000")[:6])
    return (calendar.timegm((y, mo, d, h, mi, 0)) + int(m.group(6))) * _US_PER_S + frac_us


def t_us_to_iso(t_us: int) -> str:
    """Microseconds since 1970 UTC -> ISO 8601 with a Z: milliseconds when the time is on the millisecond grid
    (the session files' usual form), microseconds otherwise."""
    t_us = int(t_us)
    if t_us % 1000 == 0:
        return _iso_ms(np.array([t_us // 1000]))[0]
    return str(np.datetime_as_string(np.datetime64(t_us, "us"), unit="us")) + "Z"


def _iso_ms(t_ms: np.ndarray) -> np.ndarray:
    """Milliseconds since 1970 UTC -> ISO strings with milliseconds and a Z (object array)."""
    stamps = np.asarray(t_ms, dtype=np.int64).astype("datetime64[ms]")
    return np.char.add(np.datetime_as_string(stamps, unit="ms"), "Z").astype(object)


# ------------------------------------------------------------------------------------------------- time series
def frame_times(t0_iso: str, interval_s: float, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame time strings (object array, ISO 8601 with ms and Z) and their UTC two-part Julian dates.

    t_k = t0 (to the millisecond below) + round(k * interval in ms), civil time arithmetic (leap seconds are not
    inserted), as :func:`iso_plus_seconds`."""
    return frame_times_range(t0_iso, interval_s, 0, frames)


def frame_times_range(
    t0_iso: str, interval_s: float, start: int, stop: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`frame_times` of frames ``start`` .. ``stop - 1`` only (the same values: a long session's times are
    made chunk by chunk)."""
    offsets_ms = np.round(np.arange(start, stop, dtype=np.float64) * interval_s * 1000.0).astype(np.int64)
    text = _iso_ms(iso_to_t_us(t0_iso) // 1000 + offsets_ms)
    jd1, jd2 = parse_iso_utc_many(text)
    return text, jd1, jd2


def iso_plus_seconds(start_iso: str, seconds: float) -> str:
    """``start_iso`` + ``seconds`` as an ISO string with milliseconds (civil time arithmetic; leap seconds are not
    inserted; the sum is rounded to the microsecond, then cut to the millisecond below)."""
    t_us = iso_to_t_us(start_iso) + round(seconds * _US_PER_S)
    return _iso_ms(np.array([t_us // 1000]))[0]
