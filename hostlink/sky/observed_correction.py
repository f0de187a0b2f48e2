"""Observation-quantity refraction correction (seed 001 sec. 3), on the host, for comparison with the onboard
reference-quantity correction (seed 001 sec. 4, :func:`onboard.refraction.refract_toward_zenith`).

Seed 001 finds the corrected image point by solving two nonlinear equations (eq. 18-19). Geometrically that point is
the observed direction w turned away from the zenith U, in the plane of w and U, by the refraction R(z_a) at the
apparent zenith distance z_a = angle(w, U) (eq. 12-13): a rotation about w x U by -R(z_a), with no solve at all.
Here R(z_a) is the model's own argument, so no approximation is involved. The zenith in sensor axes needs an
attitude: a first attitude from the uncorrected vectors (off by about R, a minute of arc) gives U_s to that accuracy,
which moves R by R'(z) * 1' < 0.001"; one more pass removes even that.

Diurnal aberration is not refraction: it belongs to the reference side in both methods. ``hostlink attitude``
passes ``r`` already aberrated by the site velocity (``onboard.refraction.topocentric_observed`` without weather),
so this module corrects the measured vectors for the atmosphere only.
"""

from __future__ import annotations

import numpy as np

from onboard.attitude import attitude_from_vectors
from onboard.refraction import (
    MIN_COS_ZENITH,
    model_coefficients,
    refraction_apparent,
    rotate_in_vertical,
    zenith_geometry,
)
from onboard.site import Weather

#: Passes of (attitude -> zenith in sensor axes -> corrected vectors); the second changes the result by < 0.001".
OBSERVED_CORRECTION_PASSES = 2


def correct_observed(
    b: np.ndarray, zenith_sensor: np.ndarray, weather: Weather, model: str = "atan", lat_rad: float | None = None
) -> np.ndarray:
    """Observed (refracted) sensor-frame directions b (N, 3) -> true directions (N, 3): each turned away from the
    zenith (given in sensor axes) by R(z_a), z_a its apparent zenith distance (seed 001 eq. 12-13, sec. 3.4)."""
    a, bb = model_coefficients(weather, model, lat_rad)
    dt = b.dtype.type
    cz, sz, tangential = zenith_geometry(b, zenith_sensor)
    refr = refraction_apparent(cz, sz, a, bb)
    limit = -dt(a) / np.maximum(cz, dt(MIN_COS_ZENITH))
    return rotate_in_vertical(b, sz, tangential, -refr, limit)


def attitude_observed_correction(
    b: np.ndarray,
    r: np.ndarray,
    zenith_ref: np.ndarray,
    weather: Weather,
    model: str = "atan",
    lat_rad: float | None = None,
    weights=None,
    passes: int = OBSERVED_CORRECTION_PASSES,
) -> tuple[np.ndarray, np.ndarray]:
    """Attitude C (b = C r) with the observation-quantity correction: returns (C, corrected b).

    ``r`` (N, 3) and ``zenith_ref`` (3,) are in the same reference frame (e.g. TOD, with the zenith from
    :func:`onboard.earth.zenith_true_of_date`, or local north-up-east with zenith (0, 1, 0)).
    """
    c = attitude_from_vectors(b, r, weights)
    b_true = b
    for _ in range(passes):
        b_true = correct_observed(b, c @ zenith_ref, weather, model, lat_rad)
        c = attitude_from_vectors(b_true, r, weights)
    return c, b_true
