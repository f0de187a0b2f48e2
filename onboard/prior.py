"""The 1-sigma prior a parameter set carries, and how the onboard estimator starts from it.

A calibrated parameter set knows how well each parameter is known: a ground calibration's ``sigma`` (its
covariance, ``hostlink.calibration.report.sigma_dict``) or the onboard estimator's own. The set carries that 1-sigma
per estimable parameter (ESTIMATE_NAMES order, parameter units: f in mm, x0 y0 in px, distortion in its own units)
in the parameter file (``sigma`` object), on every link and in the sensor's banks (``protocol.param_table``), and the
estimator restarts from the active set with it as its prior instead of the cold-start one
(``onboard.recursive.default_prior_sigma``), so a refinement keeps the calibration's accuracy.

A sigma value is NaN ("unknown") or a finite number >= 0. NaN and 0 both mean "unknown": the estimator gives that
parameter its cold-start prior (a ground calibration writes 0 for a parameter it held fixed, which says nothing about
how well it is known). A negative or infinite value is refused (:func:`validate_sigma`, raised by host and sensor alike
with the file's field name).

Correlations: the set carries marginal sigmas only, but a calibration's errors are strongly correlated (x0 with p1
and s1, y0 with p2 and s2, f with k1 k2 k3: |rho| 0.95-0.99 in ``hostlink bench``'s ground calibration). A diagonal
prior with the marginal variances, D, is then overconfident along the correlated combination, which is also the one
the onboard interstar data constrain worst (a principal-point shift equals a rotation plus p1 = -s1 = dx0 / 2F^2): a
replay started from it had normalised errors of 1.7-2.2 sigma for hundreds of frames. ``c D >= P`` (conservative)
holds for c = the largest eigenvalue of the correlation matrix, which is bounded by the size of the largest group of
mutually degenerate parameters, 4 (f k1 k2 k3), and measured at 3.7 (bench bundle calibration) and 3.9-4.0
(interstar calibrations of 100-600 frames). Each refined sigma is therefore inflated by :data:`CORRELATION_INFLATION`
= sqrt(4) = 2 before it becomes the prior; the normalised errors then stay at 0.7-1.4
(``tests/test_recursive_prior.py``).

Burn-in (``RecursiveConfig.burn_in_frames``): it fades the first frames because they are linearised far from the
truth (a cold start is 3 % of f, 5 % of the image side away) and their second-order error biases the weakly observable
principal point / decentering / thin-prism combination. That error scales with the square of the distance to the
truth; a refined prior (2.6 px on x0 in ``hostlink bench`` after the inflation, against 51 px cold) makes it some 400
times smaller, far below the noise, and the burn-in would only throw information away: it inflates the covariance by
k^2 over the first k frames, i.e. erases the prior (x 300 in sigma by frame 300), and the estimate wanders off as after
a cold start. Measured over 12 synthetic refinements (prior from a 100-frame calibration, 5.8 px on x0): with the
burn-in the x0 error grows from 6.3 px to 16.5 px RMS at frame 25 and is 7.7 px at frame 100; without it it stays at
6.5 and 6.0 px with normalised errors of 0.8-1.4, and both end at the same accuracy by frame 400 (2.9 and 3.1 px).
:func:`prior_config` therefore switches the burn-in off when every estimated parameter has a refined prior and keeps
it when any of them starts cold (the state is then still far from the truth in that direction).

Pure numpy, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from onboard.params import DISTORTION_NAMES, ESTIMATE_NAMES, N_PARAMS, CameraParams, ParameterError
from onboard.recursive import RecursiveConfig, default_prior_sigma

#: Factor applied to a refined (marginal) sigma to make the diagonal prior conservative (module docstring).
CORRELATION_INFLATION = 2.0

#: Field name of each sigma in a parameter file (``sigma`` object), ESTIMATE_NAMES order; used in refusals.
SIGMA_FILE_FIELDS: tuple[str, ...] = (
    "sigma.focal_length_mm",
    "sigma.principal_point_px[0]",
    "sigma.principal_point_px[1]",
    *(f"sigma.distortion.{k}" for k in DISTORTION_NAMES),
)


def unknown_sigma() -> np.ndarray:
    """A sigma vector with nothing known (all NaN), float64, ESTIMATE_NAMES order."""
    return np.full(N_PARAMS, np.nan, dtype=np.float64)


def validate_sigma(sigma: Sequence[float] | np.ndarray) -> None:
    """Refuse a sigma vector (ESTIMATE_NAMES order) holding a negative or infinite value (NaN = unknown is fine).
    Raises :class:`ParameterError` naming the file field, e.g. ``sigma.principal_point_px[0]``."""
    values = np.asarray(sigma, dtype=np.float64)
    if values.shape != (N_PARAMS,):
        raise ParameterError("sigma", f"expected {N_PARAMS} values, got shape {values.shape}")
    for name, v in zip(SIGMA_FILE_FIELDS, values, strict=True):
        if np.isnan(v):
            continue
        if not np.isfinite(v):
            raise ParameterError(name, f"must be finite (or NaN/null = unknown), got {float(v)!r}")
        if v < 0:
            raise ParameterError(name, f"a 1-sigma must be >= 0, got {float(v)!r}")


def sigma_from_dict(data: Mapping | None, validate: bool = True) -> np.ndarray:
    """The ``sigma`` object of a parameter file -> 10 values in ESTIMATE_NAMES order (float64, NaN = unknown).

    Accepts the parameter-file layout (``focal_length_mm``, ``principal_point_px`` [2], ``distortion`` {k1..s2}; extra
    keys such as ``fixed``/``unobservable`` are ignored) and the flat one keyed by ESTIMATE_NAMES (``f``, ``x0``...).
    null or a missing key = unknown. Raises :class:`ParameterError` naming the field (values are checked with
    :func:`validate_sigma` unless ``validate`` is False: a test hook that lets the sensor refuse them)."""
    out = unknown_sigma()
    if data is None:
        return out
    if not isinstance(data, Mapping):
        raise ParameterError("sigma", "expected an object keyed like the parameter file")

    def number(field: str, value: object) -> float:
        if value is None:
            return math.nan
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(field, f"expected a number or null, got {value!r}")
        try:
            return float(value)
        except OverflowError:  # a JSON integer beyond the float range
            raise ParameterError(field, f"an integer of {value.bit_length()} bits, beyond the float range") from None

    if "focal_length_mm" in data:
        out[0] = number(SIGMA_FILE_FIELDS[0], data["focal_length_mm"])
    if "principal_point_px" in data:
        pp = data["principal_point_px"]
        if not isinstance(pp, (list, tuple)) or len(pp) != 2:
            raise ParameterError("sigma.principal_point_px", f"expected a list of two numbers or nulls, got {pp!r}")
        out[1], out[2] = number(SIGMA_FILE_FIELDS[1], pp[0]), number(SIGMA_FILE_FIELDS[2], pp[1])
    dist = data.get("distortion")
    if dist is not None:
        if not isinstance(dist, Mapping):
            raise ParameterError("sigma.distortion", f"expected an object with keys {' '.join(DISTORTION_NAMES)}")
        for k, key in enumerate(DISTORTION_NAMES):
            if key in dist:
                out[3 + k] = number(SIGMA_FILE_FIELDS[3 + k], dist[key])
    for k, name in enumerate(ESTIMATE_NAMES):  # the flat layout (keyed f, x0, ...), also accepted on input
        if name in data:
            out[k] = number(SIGMA_FILE_FIELDS[k], data[name])
    if validate:
        validate_sigma(out)
    return out


def sigma_to_dict(sigma: Sequence[float] | np.ndarray, number=float) -> dict | None:
    """10 sigmas (ESTIMATE_NAMES order) -> the parameter file's ``sigma`` object (null = unknown; 0 is written as
    null too, since it means unknown), or None when nothing is known. ``number`` formats each value."""
    values = np.asarray(sigma, dtype=np.float64)
    known = np.isfinite(values) & (values > 0)
    if not np.any(known):
        return None
    s = [number(v) if ok else None for v, ok in zip(values, known, strict=True)]
    return {
        "focal_length_mm": s[0],
        "principal_point_px": [s[1], s[2]],
        "distortion": dict(zip(DISTORTION_NAMES, s[3:], strict=True)),
    }


def refined_mask(sigma: Sequence[float] | np.ndarray | None) -> np.ndarray:
    """Which parameters have a usable prior (finite and > 0); the others start cold."""
    if sigma is None:
        return np.zeros(N_PARAMS, dtype=bool)
    values = np.asarray(sigma, dtype=np.float64)
    return np.isfinite(values) & (values > 0)


def prior_sigma(
    nominal: CameraParams,
    sigma: Sequence[float] | np.ndarray | None,
    cold: Sequence[float] | np.ndarray | None = None,
    inflation: float = CORRELATION_INFLATION,
) -> np.ndarray:
    """The estimator's prior 1-sigma per parameter (parameter units): ``inflation`` times the set's sigma where it is
    finite and > 0 (:data:`CORRELATION_INFLATION`: the set carries marginal sigmas, not their correlations), else
    ``cold`` (default: :func:`onboard.recursive.default_prior_sigma` of ``nominal``)."""
    base = np.asarray(cold if cold is not None else default_prior_sigma(nominal), dtype=np.float64)
    mask = refined_mask(sigma)
    given = np.asarray(sigma if sigma is not None else base, dtype=np.float64)
    return np.where(mask, float(inflation) * given, base)


def prior_config(
    config: RecursiveConfig | None,
    nominal: CameraParams,
    sigma: Sequence[float] | np.ndarray | None,
    estimate: Sequence[str] = ESTIMATE_NAMES,
) -> RecursiveConfig:
    """``config`` with the prior taken from the set's ``sigma`` (:func:`prior_sigma`; ``config.prior_sigma``, when
    given, is the cold-start fallback) and the burn-in switched off when every estimated parameter starts from a
    refined prior (module docstring). With no usable sigma the config is returned unchanged (a cold start)."""
    config = config or RecursiveConfig()
    mask = refined_mask(sigma)
    if not np.any(mask):
        return config
    prior = prior_sigma(nominal, sigma, config.prior_sigma)
    idx = [ESTIMATE_NAMES.index(n) for n in estimate]
    if not bool(np.all(mask[idx])):
        return replace(config, prior_sigma=tuple(float(v) for v in prior))
    # no burn-in; the focal-drift detector, which waits for the burn-in to end, may then start as soon as its window
    # of W frames is full (a confident prior otherwise holds f still while a thermal drift runs away)
    return replace(
        config,
        prior_sigma=tuple(float(v) for v in prior),
        burn_in_frames=0,
        drift_start_frames=min(config.drift_start_frames, config.drift_window_frames),
    )
