"""UTC time stamps of session files: ISO 8601 strings <-> two-part Julian dates, and UTC -> TT / UT1 (pyerfa).

Two-part Julian dates keep sub-microsecond resolution; ERFA handles leap seconds (``dtf2d`` with scale "UTC").
"""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

import erfa
import numpy as np

_ISO = re.compile(r"^(\d{4})-(\d{2})-(\d{2})[T ](\d{2}):(\d{2}):(\d{2}(?:\.\d+)?)(Z|[+-]00:?00)?$")


def parse_iso_utc(text: str) -> tuple[int, int, int, int, int, float]:
    """Parse ``YYYY-MM-DDThh:mm:ss[.fff][Z]`` (UTC) into fields; raises ValueError with the offending text."""
    m = _ISO.match(str(text).strip())
    if not m:
        raise ValueError(f"not an ISO 8601 UTC time: {text!r} (expected e.g. 2026-03-14T02:10:00.000Z)")
    y, mo, d, h, mi = (int(m.group(k)) for k in range(1, 6))
    return y, mo, d, h, mi, float(m.group(6))


def parse_iso_utc_many(texts) -> tuple[np.ndarray, np.ndarray]:
    """ISO strings -> UTC quasi Julian dates (jd1, jd2) as ERFA expects them (dtf2d, scale "UTC")."""
    fields = [parse_iso_utc(t) for t in texts]
    if not fields:
        return np.zeros(0), np.zeros(0)
    arr = np.array(fields, dtype=np.float64)
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


def fixed_time_from_iso(text: str):
    """An ISO UTC time stamp -> ``onboard.timescale.FixedTime`` (UTC) from its calendar fields, as a sensor builds it
    (``from_calendar``, integer arithmetic). Not via ``dtf2d``: on a day with a leap second its quasi Julian date
    counts 86401 s, and reading that fraction as one of 86400 s puts the clock up to 1 s (15" of Earth rotation)
    behind."""
    from onboard.timescale import from_calendar

    y, mo, d, h, mi, s = parse_iso_utc(text)
    return from_calendar(y, mo, d, h, mi, round(s * 1_000_000))


def tai_minus_utc_s(jd_utc1: float, jd_utc2: float) -> int:
    """Leap seconds TAI - UTC [s] at a UTC two-part Julian date (``erfa.dat``): the data a sensor is given with its
    time."""
    y, m, d, fd = erfa.jd2cal(jd_utc1, jd_utc2)
    return int(round(float(erfa.dat(y, m, d, fd))))


def utc_to_tt(jd1: np.ndarray, jd2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UTC -> TT two-part Julian dates (ERFA utctai, taitt)."""
    tai1, tai2 = erfa.utctai(jd1, jd2)
    return erfa.taitt(tai1, tai2)


def utc_to_ut1(jd1: np.ndarray, jd2: np.ndarray, dut1_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """UTC -> UT1 with UT1 - UTC = dut1_s (INTERFACES.md: 0 unless --dut1 is given)."""
    return erfa.utcut1(jd1, jd2, dut1_s)


def format_iso_utc(when: datetime) -> str:
    """A datetime (naive = UTC) as the session file's ISO string with milliseconds and a Z."""
    if when.tzinfo is not None:
        when = when.astimezone(timezone.utc).replace(tzinfo=None)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def iso_plus_seconds(start_iso: str, seconds: float) -> str:
    """``start_iso`` + ``seconds`` as an ISO string (civil time arithmetic; leap seconds are not inserted)."""
    y, mo, d, h, mi, s = parse_iso_utc(start_iso)
    base = datetime(y, mo, d, h, mi) + timedelta(seconds=s)
    return format_iso_utc(base + timedelta(seconds=seconds))
