"""Frame times on the wire: int64 microseconds since 1970-01-01T00:00:00 UTC, leap seconds not counted (POSIX time),
to and from the session file's ISO 8601 strings (``protocol.messages``). Integer arithmetic throughout, so a time
with up to 6 decimals of a second survives the round trip exactly."""

from __future__ import annotations

import calendar
import re
from datetime import datetime, timedelta

from hostlink.files.times import parse_iso_utc

_EPOCH = datetime(1970, 1, 1)
_SECONDS = re.compile(r":(\d{2})(?:\.(\d+))?(?:Z|[+-]00:?00)?$")


def iso_to_t_us(text: str) -> int:
    """``2026-03-14T02:10:00.125Z`` -> microseconds since 1970 UTC (a leap second 60.x maps onto the next minute)."""
    y, mo, d, h, mi, _ = parse_iso_utc(text)
    m = _SECONDS.search(str(text).strip())
    whole, frac = m.group(1), ((m.group(2) or "") + "000000")[:6]  # parse_iso_utc accepted it, so m matches
    minute_us = calendar.timegm((y, mo, d, h, mi, 0)) * 1_000_000
    return minute_us + int(whole) * 1_000_000 + int(frac)


def t_us_to_iso(t_us: int) -> str:
    """Microseconds since 1970 UTC -> ISO 8601 with a Z: milliseconds when the time is on the millisecond grid
    (the session files' usual form), microseconds otherwise."""
    when = _EPOCH + timedelta(microseconds=int(t_us))
    text = when.strftime("%Y-%m-%dT%H:%M:%S")
    if when.microsecond % 1000 == 0:
        return f"{text}.{when.microsecond // 1000:03d}Z"
    return f"{text}.{when.microsecond:06d}Z"
