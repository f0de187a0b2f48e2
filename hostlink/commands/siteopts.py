"""Command-line site, weather and dUT1 options (docs/interfaces.md), shared by every command that takes them."""

from __future__ import annotations

import argparse
import math

from hostlink.api import Site, UserError, Weather


def _numbers(text: str, option: str, counts: tuple[int, ...], example: str) -> list[float]:
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise UserError(f"{option} {text!r}: expected numbers separated by commas, e.g. {example}") from None
    if len(values) not in counts or not all(math.isfinite(v) for v in values):
        raise UserError(f"{option} {text!r}: expected {' or '.join(map(str, counts))} finite numbers, e.g. {example}")
    return values


def parse_site(text: str) -> Site:
    """``LAT_DEG,LON_DEG,HEIGHT_M`` (east longitude positive)."""
    lat, lon, h = _numbers(text, "--site", (3,), "39.9,116.4,50")
    if not -90 <= lat <= 90:
        raise UserError(f"--site: latitude {lat} is outside [-90, 90] deg")
    if not -360 <= lon <= 360:
        raise UserError(f"--site: longitude {lon} is outside [-360, 360] deg")
    if not -500 <= h <= 10000:
        raise UserError(f"--site: height {h} m is outside [-500, 10000] m")
    return Site(lat, lon, h)


def parse_weather(text: str) -> Weather:
    """``TEMP_C,PRESSURE_HPA[,REL_HUMIDITY]`` (humidity as a fraction 0..1; a value > 1 is read as percent)."""
    values = _numbers(text, "--weather", (2, 3), "15,1013.25,0.5")
    temp, pressure = values[0], values[1]
    rh = values[2] if len(values) == 3 else 0.0
    if rh > 1.0:
        rh = rh / 100.0
    if not -80 <= temp <= 60:
        raise UserError(f"--weather: temperature {temp} C is outside [-80, 60] C")
    if not 0 <= pressure <= 1200:
        raise UserError(f"--weather: pressure {pressure} hPa is outside [0, 1200] hPa")
    if not 0 <= rh <= 1:
        raise UserError(f"--weather: relative humidity {rh} is outside [0, 1]")
    return Weather(temp, pressure, rh)


def add_site_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--site", metavar="LAT_DEG,LON_DEG,HEIGHT_M", help="ground or ship site (east longitude +)")
    parser.add_argument(
        "--weather", metavar="TEMP_C,PRESSURE_HPA[,RH]", help="weather at the site, for refraction (RH 0..1)"
    )
    parser.add_argument("--dut1", type=float, default=0.0, metavar="SECONDS", help="UT1 - UTC (default 0)")


#: IERS keeps |UT1 - UTC| below 0.9 s (docs/interfaces.md: dUT1 in seconds); anything at or above 1 s is a unit mistake.
MAX_ABS_DUT1_S = 1.0


def check_dut1(dut1_s: float) -> float:
    """--dut1 [s]: finite and within +-1 s (UT1 - UTC never leaves +-0.9 s), else a one-line UserError."""
    if not (math.isfinite(dut1_s) and abs(dut1_s) < MAX_ABS_DUT1_S):
        raise UserError(f"--dut1 {dut1_s}: UT1 - UTC is always within +-0.9 s")
    return dut1_s


def site_and_weather(args: argparse.Namespace) -> tuple[Site | None, Weather | None]:
    """Parsed --site/--weather (and a checked --dut1); --weather without --site is an error (refraction needs the
    site)."""
    check_dut1(float(getattr(args, "dut1", 0.0) or 0.0))
    site = parse_site(args.site) if getattr(args, "site", None) else None
    weather = parse_weather(args.weather) if getattr(args, "weather", None) else None
    if weather is not None and site is None:
        raise UserError("--weather needs --site (refraction depends on where the sensor is)")
    return site, weather
