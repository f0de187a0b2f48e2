"""One calibration run: pick the method, reject outliers, fit, and gather everything the result file reports."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.bundle import BundleOptions, bundle_adjust, covariance_from_normal, residuals
from hostlink.calibration.data import CalibrationData, calibration_data_from_session
from hostlink.calibration.interstar_methods import calibrate_interstar
from hostlink.calibration.report import (
    degeneracies,
    fitted_attitudes,
    interstar_rms_rad,
    residual_stats,
    sigma_dict,
)
from hostlink.calibration.robust import robust_sigma_2d, vote_consistent_stars
from hostlink.calibration.seed004 import SEED004_ESTIMATE, calibrate_seed004
from hostlink.errors import UserError
from hostlink.files.session import Session, check_on_detector
from hostlink.sky.references import SessionReferences
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams, ParameterError, validate_params
from onboard.site import Site, Weather

METHODS = ("bundle", "cosine", "sine", "improved-cosine", "improved-sine", "seed004")
#: seed 000's methods: (observation equation, two-step improved iteration of sec. 2)
INTERSTAR_METHODS = {
    "cosine": ("cos", False),
    "sine": ("sin", False),
    "improved-cosine": ("cos", True),
    "improved-sine": ("sin", True),
}
#: Gate for the interstar methods' post-fit outlier check, in robust sigmas (as the bundle's).
GATE_SIGMAS = 5.0


@dataclass
class CalibrationOutcome:
    method: str
    params: CameraParams
    theta: np.ndarray
    estimate: tuple[str, ...]
    covariance: np.ndarray
    sigma_px: float
    sigma_estimated_px: float
    data: CalibrationData  # rows used in the final fit
    attitudes: np.ndarray  # per frame of ``data``
    before: dict
    after: dict
    interstar_before_rad: float
    interstar_after_rad: float
    rejected: dict
    degeneracies: dict
    history: list[dict] = field(default_factory=list)
    converged: bool = True
    stages: list[dict] = field(default_factory=list)

    def sigma(self) -> dict:
        return sigma_dict(self.estimate, self.covariance, self.params)


def _interstar_with_gating(data, nominal, method, estimate, progress):
    theta0 = nominal.model_vector(np.float64)
    consistent = vote_consistent_stars(data, pixels_to_unit(data.x_px, data.y_px, theta0))
    fit_data, _, _ = data.select(consistent)
    if fit_data.n_frames == 0:
        raise ValueError("no frame with at least 3 consistent identified stars")
    n_gated = 0

    def fit(d):
        if method == "seed004":
            return calibrate_seed004(d, nominal, estimate or SEED004_ESTIMATE, progress=progress)
        form, improved = INTERSTAR_METHODS[method]
        return calibrate_interstar(d, nominal, form, improved, estimate or ESTIMATE_NAMES, progress=progress)

    result = fit(fit_data)
    for _ in range(2):  # gate once, refit, and confirm
        att = fitted_attitudes(fit_data, result.theta)
        norm = np.linalg.norm(residuals(fit_data, result.theta, att), axis=1)
        bad = norm > GATE_SIGMAS * robust_sigma_2d(norm)
        if not np.any(bad):
            break
        n_gated += int(bad.sum())
        fit_data = fit_data.select(~bad)[0]
        result = fit(fit_data)
    return result, fit_data, int(np.sum(~consistent)), n_gated


def calibrate(
    data: CalibrationData,
    nominal: CameraParams,
    method: str = "bundle",
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    progress: Callable[[dict], None] | None = None,
) -> CalibrationOutcome:
    """Calibrate with one of :data:`METHODS`. Raises ValueError on a problem the data cannot support.

    ``estimate`` None means the method's own set: all ten for ``bundle`` and the improved methods, (f, x0, y0) for
    ``cosine``/``sine`` (their papers' scope), (f, x0, y0, k1, k2) for ``seed004``."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    theta0 = nominal.model_vector(np.float64)
    stages: list[dict] = []
    if method == "bundle":
        options = BundleOptions(
            estimate=estimate or ESTIMATE_NAMES, noise_px=noise_px, max_iter=max_iter, progress=progress
        )
        res = bundle_adjust(data, nominal, options)
        theta, fit_data, att = res.theta, res.data, res.attitudes
        normal, est, sigma_est = res.normal, res.estimate, res.sigma_estimated_px
        u_diag = res.normal_u_diag
        rejected = {
            "voting": res.n_rejected_voting,
            "gating": res.n_rejected_gating,
            "frames_dropped": res.n_frames_dropped,
        }
        history, converged = res.history, res.converged
    else:
        fit, fit_data, n_voted, n_gated = _interstar_with_gating(data, nominal, method, estimate, progress)
        theta, normal, est, sigma_est = fit.theta, fit.normal, fit.estimate, fit.sigma_estimated_px
        att = fitted_attitudes(fit_data, theta)
        u_diag = None
        rejected = {
            "voting": n_voted,
            "gating": n_gated,
            "frames_dropped": int(data.select(np.ones(data.n_obs, bool))[0].n_frames - fit_data.n_frames),
        }
        history, converged, stages = fit.history, fit.converged, fit.stages
    rejected["total_stars"] = int(data.n_obs - fit_data.n_obs)
    sigma = float(noise_px) if noise_px else sigma_est
    cov = covariance_from_normal(normal, sigma)
    params = nominal.with_model_vector(theta)
    att_before = fitted_attitudes(fit_data, theta0)
    return CalibrationOutcome(
        method=method,
        params=params,
        theta=theta,
        estimate=est,
        covariance=cov,
        sigma_px=sigma,
        sigma_estimated_px=sigma_est,
        data=fit_data,
        attitudes=att,
        before=residual_stats(fit_data, theta0, att_before),
        after=residual_stats(fit_data, theta, att),
        interstar_before_rad=interstar_rms_rad(fit_data, theta0),
        interstar_after_rad=interstar_rms_rad(fit_data, theta),
        rejected=rejected,
        degeneracies=degeneracies(normal, est, u_diag),
        history=history,
        converged=converged,
        stages=stages,
    )


def calibrate_session(
    session: Session,
    nominal: CameraParams,
    method: str = "bundle",
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    site: Site | None = None,
    weather: Weather | None = None,
    dut1_s: float = 0.0,
    progress: Callable[[dict], None] | None = None,
) -> tuple[CalibrationOutcome, SessionReferences]:
    """Batch ground calibration of a session from the ``nominal`` camera: its identified stars against their
    reference directions (:func:`hostlink.calibration.data.calibration_data_from_session`: file or Hipparcos; with
    ``site`` observed there, with ``weather`` refracted; ``dut1_s`` = UT1 - UTC [s]), by ``method`` (:data:`METHODS`;
    ``estimate`` as in :func:`calibrate`), ``noise_px`` the centroid noise per axis [px] for the reported sigma
    (None: from the residuals), at most ``max_iter`` iterations; ``progress`` gets each iteration's record.

    Returns the outcome and the references' report. Raises :class:`UserError` (one line) for bad options, a
    centroid off the nominal's detector, a session without enough identified stars, a calibration that fails or a
    result that is not a usable parameter set (never returned as if it had succeeded)."""
    if method not in METHODS:
        raise UserError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    if noise_px is not None and not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px {noise_px}: expected a positive number of pixels")
    if max_iter < 1:
        raise UserError(f"--max-iter {max_iter}: expected at least 1")
    if len(session) == 0:
        raise UserError("no star rows in the session")
    check_on_detector(session, nominal.image_size_px, "the session", "the nominal parameters")
    data, references = calibration_data_from_session(session, site, weather, dut1_s)
    try:
        outcome = calibrate(data, nominal, method, estimate, noise_px, max_iter, progress)
    except ValueError as exc:
        raise UserError(f"calibration failed: {exc}") from None
    try:
        validate_params(outcome.params)
    except ParameterError as exc:
        raise UserError(f"the calibrated parameters are not usable ({exc}); check the nominal file") from None
    return outcome, references


def _json_safe(value):
    """Non-finite floats -> None (JSON has no NaN or Infinity), through dicts and lists."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def result_extras(outcome: CalibrationOutcome, references: SessionReferences | None = None) -> dict:
    """The extra keys of the result file (INTERFACES.md: the parameter file plus extras), with ``references``
    (where the reference directions came from) when given; non-finite numbers as null."""
    extras = {
        "method": outcome.method,
        "estimated": list(outcome.estimate),
        "sigma": outcome.sigma(),
        "noise_px": outcome.sigma_px,
        "noise_estimated_px": outcome.sigma_estimated_px,
        "residuals": {"before": outcome.before, "after": outcome.after},
        "interstar_rms_rad": {"before": outcome.interstar_before_rad, "after": outcome.interstar_after_rad},
        "n_rejected": outcome.rejected,
        "degeneracies": outcome.degeneracies,
        "iterations": len(outcome.history),
        "converged": bool(outcome.converged),
    }
    if references is not None:
        extras["references"] = {
            "source": references.source,
            "refraction": references.refraction,
            "unidentified_rows": references.n_unidentified,
        }
    return _json_safe(extras)
