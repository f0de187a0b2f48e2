"""Fixed-point time for the sensor (docs/architecture.md: no clock, time comes in with the data).

A float32 Julian date has a resolution of about 2 minutes, and a float32 Earth rotation angle one of 0.1" at best,
so time is carried as a :class:`FixedTime`: whole days since J2000.0 (int32) plus the fraction of the day in units of
2^-32 day (uint32, 20.1 us; 0.0003" of Earth rotation). Every operation on it is integer arithmetic, exact and cheap
in C; it only becomes floating point as a *difference* (Julian centuries or years since an epoch), where float32 is
plenty for precession, nutation, aberration and proper motion (a 0.001 day rounding moves none of them by 1 mas).

The time scale is the caller's: the same type holds UTC, UT1 (UTC + dUT1) or TT (UTC + TAI-UTC + 32.184 s).
Days are counted from JD 2451545.0 of that scale (2000-01-01 12:00). UTC days containing a leap second are not
modelled (the fraction is of an 86400 s day, as in ERFA's quasi Julian dates away from the leap second itself).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: 2^32: fraction-of-day units per day.
FRAC_UNITS_PER_DAY = 1 << 32
#: Seconds per day and TT - TAI (s).
SECONDS_PER_DAY = 86400
TT_MINUS_TAI_S = 32.184
#: TAI - UTC since 2017-01-01 (IERS Bulletin C); the sensor receives the current value as data.
DEFAULT_TAI_MINUS_UTC_S = 37
#: Julian date of the day count's origin, J2000.0.
JD_J2000 = 2451545.0
DAYS_PER_JULIAN_CENTURY = 36525.0
DAYS_PER_JULIAN_YEAR = 365.25


@dataclass(frozen=True)
class FixedTime:
    """An instant (or an array of instants) in some time scale, in fixed point.

    ``day``: int32 whole days since J2000.0 (JD 2451545.0, 12:00) of the scale; ``frac``: uint32 fraction of the day
    in units of 2^-32 day. Both have the same shape (a 0-d array for one instant).
    """

    day: np.ndarray
    frac: np.ndarray


def make_time(day, frac) -> FixedTime:
    """A :class:`FixedTime` from integer day count(s) and 2^-32-day fraction(s) (cast to int32 / uint32)."""
    return FixedTime(np.asarray(day, dtype=np.int32), np.asarray(frac, dtype=np.uint32))


def _normalise(day_i64: np.ndarray, frac_i64: np.ndarray) -> FixedTime:
    """Carry whole days out of an int64 fraction (any sign) and pack."""
    carry = np.floor_divide(frac_i64, FRAC_UNITS_PER_DAY)
    return make_time(day_i64 + carry, frac_i64 - carry * FRAC_UNITS_PER_DAY)


def julian_day_number(year, month, day) -> np.ndarray:
    """Gregorian calendar date -> Julian Day Number (the JD at noon of that date), integer arithmetic only.

    Fliegel & Van Flandern (1968), Comm. ACM 11, 657; valid for any Gregorian date after 4801 BC.
    """
    y = np.asarray(year, dtype=np.int64)
    m = np.asarray(month, dtype=np.int64)
    d = np.asarray(day, dtype=np.int64)
    a = np.where(m <= 2, -1, 0).astype(np.int64)  # the paper's (m - 14) / 12 with C's truncating division
    return (
        (1461 * (y + 4800 + a)) // 4 + (367 * (m - 2 - 12 * a)) // 12 - (3 * ((y + 4900 + a) // 100)) // 4 + d - 32075
    )


def from_calendar(year, month, day, hour, minute, microsecond_of_minute) -> FixedTime:
    """Calendar date and time of day (integers; seconds as integer microseconds of the minute) -> FixedTime.

    This is what a sensor does with a GPS or host time stamp: integer arithmetic only. The fraction is rounded to the
    nearest 2^-32 day (10 us at worst).
    """
    jdn = julian_day_number(year, month, day)
    us_of_day = (np.asarray(hour, np.int64) * 60 + np.asarray(minute, np.int64)) * 60_000_000 + np.asarray(
        microsecond_of_minute, np.int64
    )
    us_since_noon = us_of_day - 43_200_000_000
    # fraction = us * 2^32 / 86400e6 = us * 2^21 / 42187500 (keeps the product inside int64), rounded
    frac = (us_since_noon * (1 << 21) + 21_093_750) // 42_187_500
    return _normalise(jdn - 2451545, frac)


def from_julian_date(jd1, jd2) -> FixedTime:
    """Two-part Julian date (host side, float64) -> FixedTime, rounded to 2^-32 day. The fraction is read as one of an
    86400-s day: not for a UTC quasi Julian date (erfa.dtf2d) of a leap-second day, whose fraction counts 86401 s
    (up to 1 s off; use :func:`from_calendar`)."""
    a = np.asarray(jd1, dtype=np.float64) - JD_J2000
    b = np.asarray(jd2, dtype=np.float64)
    ai, bi = np.floor(a), np.floor(b)
    frac = np.rint(((a - ai) + (b - bi)) * FRAC_UNITS_PER_DAY).astype(np.int64)
    return _normalise((ai + bi).astype(np.int64), frac)


def to_julian_date(t: FixedTime) -> tuple[np.ndarray, np.ndarray]:
    """FixedTime -> two-part Julian date (float64), for host-side comparisons with ERFA."""
    return JD_J2000 + t.day.astype(np.float64), t.frac.astype(np.float64) / FRAC_UNITS_PER_DAY


def add_seconds(t: FixedTime, seconds) -> FixedTime:
    """t + seconds (dUT1, TAI-UTC, TT-TAI, exposure offsets). The offset is rounded to 2^-32 day (10 us)."""
    s = np.asarray(seconds)
    units = np.rint(s * (FRAC_UNITS_PER_DAY / SECONDS_PER_DAY)).astype(np.int64)
    return _normalise(t.day.astype(np.int64), t.frac.astype(np.int64) + units)


def ut1_from_utc(t_utc: FixedTime, dut1_s: float = 0.0) -> FixedTime:
    """UT1 = UTC + dUT1 (docs/interfaces.md: dUT1 = 0 unless given; |dUT1| < 0.9 s)."""
    return add_seconds(t_utc, dut1_s)


def tt_from_utc(t_utc: FixedTime, tai_minus_utc_s: int = DEFAULT_TAI_MINUS_UTC_S) -> FixedTime:
    """TT = UTC + (TAI - UTC) + 32.184 s. TAI - UTC (leap seconds) is data the sensor is given.

    A wrong leap-second count by a few seconds moves the apparent place by < 0.001" (aberration turns by 20" a
    year), so a stale value is harmless there; Earth rotation uses UT1, never TT.
    """
    return add_seconds(t_utc, float(tai_minus_utc_s) + TT_MINUS_TAI_S)


def days_since_j2000(t: FixedTime, dtype=np.float32) -> np.ndarray:
    """Days since J2000.0 of the scale as a floating value of ``dtype`` (float32 resolution: 0.001 d in 2050)."""
    dt = np.dtype(dtype)
    return t.day.astype(dt) + t.frac.astype(dt) * dt.type(1.0 / FRAC_UNITS_PER_DAY)


def julian_centuries(t: FixedTime, dtype=np.float32) -> np.ndarray:
    """Julian centuries since J2000.0 (the ``t`` of the IAU precession and nutation series)."""
    return days_since_j2000(t, dtype) / np.dtype(dtype).type(DAYS_PER_JULIAN_CENTURY)
