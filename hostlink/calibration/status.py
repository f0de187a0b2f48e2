"""The calibration status a result file carries (issue 31; docs/file-formats.md ``status``): whether the batch
calibration or the replayed onboard estimator converged, so that ``hostlink upload`` never sends a failed set."""

from __future__ import annotations

import numpy as np

from hostlink.files.params import STATUS_CONVERGED, STATUS_FAILED, STATUS_NOT_CONVERGED, status_fields
from onboard import recursive
from onboard.firmware import estimate_convergence
from onboard.params import ESTIMATE_NAMES
from protocol.messages import Estimate


def calibration_status(outcome) -> dict:
    """``status`` / ``status_reason`` of a batch calibration (:class:`hostlink.calibration.run.CalibrationOutcome`):
    ``not_converged`` when the fit reached its iteration limit, ``failed`` when it converged to a result that must not
    be used (:meth:`CalibrationOutcome.failure`: most stars rejected), else ``converged``."""
    failure = outcome.failure()
    if not outcome.converged:
        return status_fields(STATUS_NOT_CONVERGED, failure)
    if failure:
        return status_fields(STATUS_FAILED, failure)
    return status_fields(STATUS_CONVERGED)


def replay_status(state: recursive.RecursiveState) -> dict:
    """``status`` / ``status_reason`` of a replayed onboard estimate (its final ``state``, started from its nominal):
    the rule the sensor's ``accept`` applies (:func:`onboard.firmware.estimate_convergence`: enough updates, each
    estimated parameter's 1-sigma well inside its cold-start prior), so a replayed set is judged as the sensor's."""
    sigma = np.full(len(ESTIMATE_NAMES), np.nan)
    for name, value in recursive.sigma(state).items():
        sigma[ESTIMATE_NAMES.index(name)] = value
    mask = sum(1 << ESTIMATE_NAMES.index(name) for name in state.names)
    estimate = Estimate(estimated_mask=mask, n_updates=int(state.updates), sigma=tuple(float(s) for s in sigma))
    reason = estimate_convergence(state.nominal, estimate)
    return status_fields(STATUS_NOT_CONVERGED, reason) if reason else status_fields(STATUS_CONVERGED)
