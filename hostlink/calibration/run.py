"""One calibration run: pick the method, reject outliers, fit, and gather everything the result file reports.

The default method, ``bundle``, is :func:`hostlink.calibration.chunked.calibrate_chunks` whatever the input: the
session in memory as one chunk here, a session read from files in chunks by
:func:`hostlink.calibration.chunked.calibrate_archive`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hostlink.calibration.chunked import calibrate_archive, calibrate_chunks
from hostlink.calibration.data import CalibrationData, calibration_data_from_session
from hostlink.calibration.interstar_methods import calibrate_interstar
from hostlink.calibration.model import residuals
from hostlink.calibration.normal import covariance_from_normal
from hostlink.calibration.outcome import (
    CalibrationOutcome,
    ReferencesSummary,
    check_focal_scale,
    check_result,
    check_run_options,
    prepass_report,
    prepass_start,
    result_extras,
    time_unknown_note,
)
from hostlink.calibration.rejected import rejected_stars
from hostlink.calibration.report import (
    degeneracies,
    fitted_attitudes,
    interstar_rms_rad,
    residual_stats,
)
from hostlink.calibration.robust import max_pair_angle_rad, robust_sigma_2d, vote_consistent_stars
from hostlink.calibration.seed004 import SEED004_ESTIMATE, calibrate_seed004
from hostlink.calibration.source import in_memory_source
from hostlink.errors import UserError
from hostlink.files.session import Session, check_on_detector
from hostlink.sky.references import SessionReferences
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams
from onboard.site import Site, Weather

#: What other modules import from here: the run's entry points and its outcome.
__all__ = [
    "METHODS",
    "CalibrationOutcome",
    "ReferencesSummary",
    "calibrate",
    "calibrate_archive",
    "calibrate_chunks",
    "calibrate_session",
    "result_extras",
    "time_unknown_note",
]

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


def _interstar_with_gating(data, start, method, estimate, progress, consistent):
    fit_data, _, _ = data.select(consistent)
    if fit_data.n_frames == 0:
        raise ValueError("no frame with at least 3 consistent identified stars")
    gated = np.zeros(data.n_obs, dtype=bool)
    index = np.searchsorted(data.source_rows(), fit_data.source_rows())  # input row of each fit row (increasing)

    def fit(d):
        if method == "seed004":
            return calibrate_seed004(d, start, estimate or SEED004_ESTIMATE, progress=progress)
        form, improved = INTERSTAR_METHODS[method]
        return calibrate_interstar(d, start, form, improved, estimate or ESTIMATE_NAMES, progress=progress)

    result = fit(fit_data)
    for _ in range(2):  # gate once, refit, and confirm
        att = fitted_attitudes(fit_data, result.theta)
        norm = np.linalg.norm(residuals(fit_data, result.theta, att), axis=1)
        bad = norm > GATE_SIGMAS * robust_sigma_2d(norm)
        if not np.any(bad):
            break
        gated[index[bad]] = True
        fit_data, kept, _ = fit_data.select(~bad)
        index = index[kept]
        result = fit(fit_data)
    return result, fit_data, gated


def calibrate(
    data: CalibrationData,
    nominal: CameraParams,
    method: str = "bundle",
    estimate: tuple[str, ...] | None = None,
    noise_px: float | None = None,
    max_iter: int = 100,
    progress: Callable[[dict], None] | None = None,
    noise_model: str = "auto",
    mirror_fit: bool = True,
) -> CalibrationOutcome:
    """Calibrate with one of :data:`METHODS`. Raises ValueError on a problem the data cannot support (among them
    a mirrored image, :func:`mirrored_message`).

    1. Pre-pass (:func:`prepass_start`): the focal length from the identified stars' interstar angles (when f is
       estimated) and the parity, so a nominal focal length far off (0.1 to 10 tested) starts where a good one would.
    2. Interstar voting (``robust.vote_consistent_stars``) at that camera.
    3. The fit. ``estimate`` None means the method's own set: for ``bundle`` every parameter the data determine
       (all ten, less those :func:`hostlink.calibration.report.undetermined_parameters` holds at nominal, which
       ``held`` lists with the reason); all ten for the improved methods, (f, x0, y0) for ``cosine``/``sine``
       (their papers' scope), (f, x0, y0, k1, k2) for ``seed004``. An explicit ``estimate`` is used as given.
       ``noise_model`` (stars of given sigma_px, bundle): "auto", the noise floor constant or growing with the field
       radius as the data choose (:mod:`hostlink.calibration.noisefield`); "constant", the constant one only.
       ``mirror_fit`` (bundle): as in :func:`hostlink.calibration.chunked.calibrate_chunks`."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
    if method == "bundle":
        options = {"keep_data": data, "noise_model": noise_model, "mirror_fit": mirror_fit}
        return calibrate_chunks(in_memory_source(data), nominal, estimate, noise_px, max_iter, progress, **options)
    theta0 = nominal.model_vector(np.float64)
    start, prepass = prepass_start(data, nominal, estimate is None or "f" in estimate)
    consistent = vote_consistent_stars(data, pixels_to_unit(data.x_px, data.y_px, start.model_vector(np.float64)))
    voted_out = ~consistent
    check_focal_scale(prepass, start is nominal, not np.any(consistent))
    fit, fit_data, gated = _interstar_with_gating(data, start, method, estimate, progress, consistent)
    theta, normal, est, sigma_est = fit.theta, fit.normal, fit.estimate, fit.sigma_estimated_px
    att = fitted_attitudes(fit_data, theta)
    history, converged, stages = fit.history, fit.converged, fit.stages
    rejected = {
        "voting": int(np.sum(voted_out)),
        "gating": int(np.sum(gated)),
        "frames_dropped": int(data.n_frames - fit_data.n_frames),
        "total_stars": int(data.n_obs - fit_data.n_obs),
    }
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
        degeneracies=degeneracies(normal, est),  # the seed methods have no attitude blocks to compare with
        history=history,
        converged=converged,
        stages=stages,
        prepass=prepass_report(prepass, nominal, start),
        not_converged_reason=getattr(fit, "failure", None),
        voted_out=voted_out,
        gated=gated,
        n_stars_used=fit_data.n_obs,
        n_frames_used=fit_data.n_frames,
        field_rad=max_pair_angle_rad(fit_data),
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
    keep_failed: bool = False,
    noise_model: str = "auto",
    mirror_fit: bool = True,
) -> tuple[CalibrationOutcome, SessionReferences]:
    """Batch ground calibration of a session from the ``nominal`` camera: its identified stars against their
    reference directions (:func:`hostlink.calibration.data.calibration_data_from_session`: file or Hipparcos; with
    ``site`` observed there, with ``weather`` refracted; ``dut1_s`` = UT1 - UTC [s]; with the time unknown J2000
    directions, :func:`time_unknown_note`), by ``method`` (:data:`METHODS`; ``estimate`` as in :func:`calibrate`),
    ``noise_px`` the centroid noise per axis [px] for the reported sigma (None: from the residuals), at most
    ``max_iter`` iterations; ``progress`` gets each iteration's record; ``noise_model`` and ``mirror_fit`` as in
    :func:`calibrate`.

    Returns the outcome (with its ``rejected_stars`` and ``time_note``) and the references' report. A result that
    did not converge or rejected most stars (:meth:`CalibrationOutcome.failure`) raises :class:`UserError`, unless
    ``keep_failed``: then it is returned, and the caller must check ``outcome.failure()`` before using it. Also raises
    :class:`UserError` (one line) for bad options, a centroid off the nominal's detector, a session without enough
    identified stars, a mirrored image, a calibration that fails or a result that is not a usable parameter set."""
    if method not in METHODS:
        raise UserError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    check_run_options(noise_px, max_iter, noise_model)
    if len(session) == 0:
        raise UserError("no star rows in the session")
    check_on_detector(session, nominal.image_size_px, "the session", "the nominal parameters")
    data, references = calibration_data_from_session(session, site, weather, dut1_s)
    try:
        outcome = calibrate(data, nominal, method, estimate, noise_px, max_iter, progress, noise_model, mirror_fit)
    except ValueError as exc:
        raise UserError(f"calibration failed: {exc}") from None
    check_result(outcome, keep_failed)
    outcome.rejected_stars = rejected_stars(session, references, data, outcome)
    outcome.time_note = None if references.time_known else time_unknown_note(outcome)
    return outcome, references
