"""What a calibration run gives: the outcome, the pre-pass's start and report, the failure rule and the result
file's extras (shared by the in-memory and the chunked runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.floorfit import radial_allowed
from hostlink.calibration.model import ARCSEC_PER_RAD
from hostlink.calibration.rejected import (
    REASON_FEW_IN_FRAME,
    REASON_FRAME_LEFT,
    REASON_GATING,
    REASON_UNKNOWN_ID,
    REASON_VOTING,
    RejectedStars,
)
from hostlink.calibration.report import sigma_dict
from hostlink.calibration.robust import VOTE_REL_TOL, ScaleParity, estimate_scale_and_parity, max_pair_angle_rad
from hostlink.errors import UserError
from hostlink.sky.references import ABERRATION_MAX_RAD, SessionReferences
from onboard.params import CameraParams, ParameterError, validate_params

#: A calibration that rejects more than this fraction of the identified stars it was given (interstar voting,
#: residual gating, and the stars of frames left with fewer than three) has failed: most of its input disagrees
#: with the camera it found, so the camera describes a minority (a wrong nominal or wrong identifications).
MAX_REJECTED_FRACTION = 0.5


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
    #: the pre-pass before voting (:func:`hostlink.calibration.robust.estimate_scale_and_parity`), as reported
    prepass: dict = field(default_factory=dict)
    #: parameters held at nominal because the data cannot determine them (:func:`report.undetermined_parameters`)
    held: list[dict] = field(default_factory=list)
    #: the rows of the input data: rejected by interstar voting, and by residual gating (bool, input rows)
    voted_out: np.ndarray | None = None
    gated: np.ndarray | None = None
    #: set by :func:`calibrate_session`: every identified star of the session not used, and the note on the loss
    #: of a session without time (None when the time is known)
    rejected_stars: RejectedStars | None = None
    time_note: str | None = None
    #: stars and frames of the final fit (the chunked path has no ``data`` in memory: ``data`` is None there)
    n_stars_used: int = 0
    n_frames_used: int = 0
    #: the largest catalogue angle between two stars of one frame [rad] (for :func:`time_unknown_note`)
    field_rad: float = float("nan")
    #: the chunked path's counts of the rejected stars by reason (``rejected_stars`` needs the session in memory)
    rejected_by_reason: dict | None = None
    #: why a fit that did not converge stopped, naming what its model cannot separate (the seed methods')
    not_converged_reason: str | None = None
    #: stars weighted by the session's sigma_px: the fitted noise relative to the given one (its sigma_px and
    #: sigma_estimated_px are then this scale, not pixels); None: one noise for every star, in ``sigma_px``
    noise_scale: float | None = None
    #: stars weighted by the session's sigma_px: the noise floor common to the session [px], each star's noise per
    #: axis sqrt((noise_scale sigma_px)^2 + noise_floor_px^2) (hostlink.calibration.noisefloor); None otherwise
    noise_floor_px: float | None = None
    #: the floor at the half-diagonal from the nominal principal point [px] (= noise_floor_px for a constant floor),
    #: the noise model's record (hostlink.calibration.floorfit.noise_model_record: which model, its components and
    #: their standard errors, the likelihood ratio) and the model the weights used (noisefloor.NoiseModel)
    noise_floor_edge_px: float | None = None
    noise_model: dict | None = None
    noise_weights: object | None = None
    #: why the fit stopped (:class:`hostlink.calibration.lm.Status` of the bundle's last round; None: other methods)
    status: str | None = None

    def sigma(self) -> dict:
        return sigma_dict(self.estimate, self.covariance, self.params)

    def failure(self) -> str | None:
        """Why this result must not be used as a calibration (one line), or None: the fit did not converge, or
        more than :data:`MAX_REJECTED_FRACTION` of the identified stars were rejected."""
        if not self.converged:
            if self.not_converged_reason:
                return self.not_converged_reason
            return (
                f"the fit did not converge: it reached the iteration limit ({len(self.history)} iterations) still "
                "moving; raise --max-iter, or check the nominal and the identifications"
            )
        rej = self.rejected
        n_in = self.n_stars_used + rej["total_stars"]
        if n_in and rej["total_stars"] > MAX_REJECTED_FRACTION * n_in:
            return (
                f"{rej['total_stars']} of {n_in} identified stars ({100 * rej['total_stars'] / n_in:.0f} %, more "
                f"than {100 * MAX_REJECTED_FRACTION:.0f} %) were rejected ({rej['voting']} by interstar voting, "
                f"{rej['gating']} by residual gating, the rest with their frames): the identifications or the "
                "nominal are wrong"
            )
        return None


def mirrored_message(prepass: ScaleParity, image_size_px: tuple[int, int]) -> str:
    """The one-line explanation of a mirrored detector (odd parity) and how to fix it."""
    return (
        f"the image is mirrored: odd parity (in {100 * prepass.mirrored_fraction:.0f} % of {prepass.n_triples} "
        "star triples the handedness in the camera frame is opposite to the sky's, which no rotation can do); flip "
        f"x (x_px -> {image_size_px[0] - 1} - x_px) in the session or in the sensor's readout, then calibrate again"
    )


def prepass_start(data: CalibrationData, nominal: CameraParams, scale_focal: bool) -> tuple[CameraParams, ScaleParity]:
    """The camera the fit starts from: the nominal with its focal length scaled by what the identified stars say
    (when ``scale_focal``), after checking the parity. Raises ValueError for a mirrored image."""
    prepass = estimate_scale_and_parity(data, nominal.model_vector(np.float64))
    return start_from_prepass(prepass, nominal, scale_focal), prepass


def start_from_prepass(prepass: ScaleParity, nominal: CameraParams, scale_focal: bool) -> CameraParams:
    """The camera the fit starts from, given the pre-pass (:func:`prepass_start`). Raises ValueError for a
    mirrored image."""
    if prepass.mirrored:
        raise ValueError(mirrored_message(prepass, nominal.image_size_px))
    if not scale_focal or prepass.n_pairs == 0:
        return nominal
    return nominal.with_focal_length_mm(nominal.focal_length_mm * prepass.scale)


def check_run_options(noise_px: float | None, max_iter: int, noise_model: str = "auto") -> None:
    """UserError (one line, naming the option) for a noise that is not a positive number of pixels, fewer than one
    iteration or an unknown ``noise_model`` (:data:`hostlink.calibration.floorfit.NOISE_MODELS`; refused whether
    or not the session has sigma_px): the options every calibration run takes."""
    if noise_px is not None and not (math.isfinite(noise_px) and noise_px > 0):
        raise UserError(f"--noise-px {noise_px}: expected a positive number of pixels")
    if max_iter < 1:
        raise UserError(f"--max-iter {max_iter}: expected at least 1")
    try:
        radial_allowed(noise_model)
    except ValueError as exc:
        raise UserError(f"noise_model: {exc}") from None


def check_focal_scale(prepass: ScaleParity, from_nominal: bool, none_agrees: bool) -> None:
    """ValueError when no star agreed with the catalogue at a nominal focal length (``from_nominal``: the fit was
    not asked to estimate f, so the pre-pass did not rescale it) that the stars' own interstar angles say is off by
    more than the vote's relative tolerance (:data:`hostlink.calibration.robust.VOTE_REL_TOL`)."""
    if from_nominal and prepass.n_pairs and abs(prepass.scale - 1.0) > VOTE_REL_TOL and none_agrees:
        raise ValueError(
            f"no star agrees with the catalogue at the nominal focal length, which the stars say is "
            f"{100 * (1 / prepass.scale - 1):+.1f} % off: estimate f"
        )


def prepass_report(prepass: ScaleParity, nominal: CameraParams, start: CameraParams) -> dict:
    """The pre-pass as the result file reports it."""
    return {
        "focal_scale": prepass.scale,
        "scale_pairs": prepass.n_pairs,
        "nominal_focal_length_mm": nominal.focal_length_mm,
        "start_focal_length_mm": start.focal_length_mm,
        "mirrored_fraction": prepass.mirrored_fraction,
        "parity_triples": prepass.n_triples,
    }


def time_unknown_note(outcome: CalibrationOutcome) -> str:
    """The stated loss of a calibration against J2000 directions (the session gave no time): annual aberration
    (up to :data:`hostlink.sky.references.ABERRATION_MAX_RAD`) is left in the references. Its differential part over
    the field changes interstar angles by up to 20.5" x the angle [rad]: a scale error of up to 1.0e-4 in the focal
    length, and up to 20.5" x the field's largest pair angle in the directions."""
    field_rad = outcome.field_rad if outcome.data is None else max_pair_angle_rad(outcome.data)
    focal_px = float(outcome.theta[0])
    return (
        "time unknown: reference directions are J2000 catalogue places; precession and nutation are absorbed by "
        f"the per-frame attitudes, annual aberration is not: interstar angles may be off by up to "
        f'{ABERRATION_MAX_RAD * ARCSEC_PER_RAD * field_rad:.2g}" over this field ({math.degrees(field_rad):.3g} deg), '
        f"the focal length by up to {ABERRATION_MAX_RAD:.1e} relative ({ABERRATION_MAX_RAD * focal_px:.2g} px); "
        "proper motion since the directions' epoch (Hipparcos: J2000.0) is not applied either. If the date is "
        'known, give it as t_utc (any time that day: the aberration then errs by at most 0.18")'
    )


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
    """The extra keys of the result file (docs/file-formats.md: the parameter file plus extras), with ``references``
    (where the reference directions came from) when given; non-finite numbers as null. Also the rejected stars by
    reason and the time note when :func:`calibrate_session` set them, and ``failed`` (the reason) for a failed
    result kept on request; ``status`` / ``status_reason`` (:mod:`hostlink.calibration.status`)."""
    extras = {
        "method": outcome.method,
        "estimated": list(outcome.estimate),
        "sigma": outcome.sigma(),
        "noise_px": outcome.sigma_px if outcome.noise_scale is None else None,
        "noise_estimated_px": outcome.sigma_estimated_px if outcome.noise_scale is None else None,
        "residuals": {"before": outcome.before, "after": outcome.after},
        "interstar_rms_rad": {"before": outcome.interstar_before_rad, "after": outcome.interstar_after_rad},
        "n_rejected": outcome.rejected,
        "degeneracies": outcome.degeneracies,
        "iterations": len(outcome.history),
        "converged": bool(outcome.converged),
        "stopped": outcome.status,  # the bundle's last round's lm.Status text (None: the seed methods)
        "held": outcome.held,
        "prepass": outcome.prepass,
    }
    if references is not None:
        extras["references"] = {
            "source": references.source,
            "refraction": references.refraction,
            "unidentified_rows": references.n_unidentified,
            "unknown_star_ids": int(references.unknown_rows.size),  # rows: in the --rejected file
            "time_known": references.time_known,
        }
    if outcome.rejected_stars is not None:
        extras["rejected_by_reason"] = outcome.rejected_stars.counts()
    elif outcome.rejected_by_reason is not None:
        extras["rejected_by_reason"] = outcome.rejected_by_reason
    if outcome.time_note:
        extras["time_unknown"] = outcome.time_note
    if outcome.noise_scale is not None:
        extras["noise_scale"] = outcome.noise_scale  # fitted noise / the session's sigma_px
        extras["noise_floor_px"] = outcome.noise_floor_px  # the noise floor added to it in quadrature [px]
        extras["noise_floor_edge_px"] = outcome.noise_floor_edge_px  # the floor at the half-diagonal [px]
        extras["noise_model"] = outcome.noise_model  # constant or radial, components, sigmas, likelihood ratio
    failure = outcome.failure()
    if failure:
        extras["failed"] = failure
    from hostlink.calibration.status import calibration_status

    extras.update(calibration_status(outcome))  # upload refuses a set that is not converged
    return _json_safe(extras)


@dataclass(frozen=True)
class ReferencesSummary:
    """Where the reference directions of a chunked session came from (the fields of
    :class:`hostlink.sky.references.SessionReferences` the result file reports), over all its chunks."""

    source: str
    refraction: str
    n_unidentified: int
    unknown_rows: np.ndarray  # session rows (counted through all files) whose star_id Hipparcos does not have
    time_known: bool
    #: identified stars with a reference direction in frames with fewer than three of them (not calibration data)
    n_few_in_frame: int = 0


def rejected_counts(outcome: CalibrationOutcome, references: ReferencesSummary) -> dict[str, int]:
    """The stars of a chunked session the calibration did not use, counted by reason (the ``REASON_*`` texts of
    :func:`hostlink.calibration.rejected.rejected_stars`, those with a count): unknown star ids, frames with fewer
    than three identified stars, voting, gating, and frames left with fewer than three after those."""
    rej = outcome.rejected
    counts = {
        REASON_UNKNOWN_ID: int(references.unknown_rows.size),
        REASON_FEW_IN_FRAME: int(references.n_few_in_frame),
        REASON_VOTING: int(rej["voting"]),
        REASON_GATING: int(rej["gating"]),
        REASON_FRAME_LEFT: int(rej["total_stars"] - rej["voting"] - rej["gating"]),
    }
    return {reason: n for reason, n in sorted(counts.items()) if n}


def check_result(outcome: CalibrationOutcome, keep_failed: bool) -> None:
    """Raise UserError for a failed result (unless ``keep_failed``) or unusable parameters."""
    failure = outcome.failure()
    if failure is not None and not keep_failed:
        raise UserError(f"calibration failed: {failure}")
    if failure is None:
        try:
            validate_params(outcome.params)
        except ParameterError as exc:
            raise UserError(f"the calibrated parameters are not usable ({exc}); check the nominal file") from None


#: A nominal's focal length is within 10-20 % of the lens's (design values, a stock lens); a pixel pitch that leaves
#: out a 2 x 2 binning makes it 2 x (or 1/2 x) that, so a factor within this of 2 points to the pitch.
BINNING_FACTOR_TOLERANCE = 1.25


def focal_hint(ratio: float) -> str:
    """What a focal length ``ratio`` x the nominal's found from the stars points to, as the text ``calibrate`` appends
    to its line: a factor near 2 (within :data:`BINNING_FACTOR_TOLERANCE`) to a binning left out of the pixel pitch;
    a larger one to a nominal that is not this camera's; a smaller one to nothing (nominals are that far off)."""
    factor = abs(math.log(ratio))
    if abs(factor - math.log(2.0)) <= math.log(BINNING_FACTOR_TOLERANCE):
        return " (a factor near 2: check the pixel pitch for binning)"
    if factor > math.log(2.0):
        return " (check that the nominal is this camera's: focal length, pixel pitch, image size)"
    return ""
