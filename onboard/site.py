"""Observing site and weather (docs/interfaces.md): plain data shared by the sensor model and the host.

Longitude is east-positive. Relative humidity is a fraction 0..1. Wavelength defaults to 0.55 um (visual), the
effective wavelength of a silicon star sensor being a user choice.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Site:
    lat_deg: float
    lon_deg: float
    height_m: float = 0.0


@dataclass(frozen=True)
class Weather:
    temp_c: float
    pressure_hpa: float
    rel_humidity: float = 0.0
    wavelength_um: float = 0.55
