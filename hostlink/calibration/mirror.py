"""The principal point with decentering and prism free (docs/calibration.md, "Principal point with decentering and
prism free"): a shift of the principal point with p and -s grown by d / (2 F^2) moves no star to first order, so the
cost has a second, mirrored minimum; the fit is run again from it and reported beside the first."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hostlink.calibration.bundle import BundleOptions, ChunkedBundleResult, bundle_adjust_chunks
from hostlink.calibration.passes import PassRunner
from hostlink.calibration.report import degeneracies, stats_from_sums
from hostlink.calibration.source import ChunkSource
from onboard.params import ESTIMATE_NAMES, CameraParams

#: A mirrored principal point (its start, or where its fit ends) within this many of the fit's 1-sigma of the fit's
#: own in both coordinates is the same minimum: 3 sigma, beyond which a Gaussian posterior puts 0.3 % of its mass.
MIRROR_SAME_SIGMAS = 3.0


def prism_shift_direction(axis: int, focal_px: float) -> np.ndarray:
    """The change of the model vector (F, x0, y0, k1, k2, k3, p1, p2, s1, s2) per px of principal-point shift along
    ``axis`` (0: x0, 1: y0) that moves no star to first order once each frame's attitude is re-fitted.

    Shifting the principal point by d along y changes every measured offset (u, v) by (0, -d); the rotation that best
    re-centres the frame (by d / F about the detector's x axis) moves a star at (u, v) by d (u v, F^2 + v^2) / F^2
    in the gnomonic projection, leaving d (u v, v^2) / F^2. The distortion of :func:`onboard.camera.distortion_px`
    (seed 000 eq. 7) with p2 = -s2 = c is (dx, dy) = 2 c v (u, v): the same field for c = d / (2 F^2). So (y0, p2,
    s2) moved by (1, 1 / (2 F^2), -1 / (2 F^2)) per px leaves the stars where they were but for terms of order
    d^2 / F^2 and d k1 r^2; likewise (x0, p1, s1)."""
    step = np.zeros(10, dtype=np.float64)
    coefficient = 1.0 / (2.0 * focal_px * focal_px)
    step[1 + axis] = 1.0
    step[6 + axis] = coefficient
    step[8 + axis] = -coefficient
    return step


def mirror_is_distinct(theta: np.ndarray, mirrored: np.ndarray, sigma: np.ndarray) -> bool:
    """Whether the mirrored start (:func:`mirrored_principal_point`) is at least :data:`MIRROR_SAME_SIGMAS` of this
    fit's 1-sigma ``sigma`` (model vector) from ``theta`` in x0 or y0: else it is this minimum and no fit is run."""
    return bool(np.any(np.abs(mirrored[1:3] - theta[1:3]) >= MIRROR_SAME_SIGMAS * sigma[1:3]))


def mirrored_principal_point(theta: np.ndarray, prism: list[dict]) -> np.ndarray:
    """The camera ``theta`` with each principal-point coordinate of ``prism``
    (:func:`hostlink.calibration.report.principal_point_prism`) reflected along :func:`prism_shift_direction` about the
    point where its decentering equals its prism (p = s; p and -s grow by d / (2 F^2) per px of shift, so that point is
    d = F^2 (p - s) px away): the other minimum the second-order terms leave, where a fit started there ends."""
    out = np.array(theta, dtype=np.float64, copy=True)
    focal_px = float(theta[0])
    for item in prism:
        axis = 0 if item["parameter"] == "x0" else 1
        shift_px = focal_px * focal_px * (theta[6 + axis] - theta[8 + axis])
        out -= 2.0 * shift_px * prism_shift_direction(axis, focal_px)
    return out


def mirror_report(prism: list[dict], theta: np.ndarray, sigma: np.ndarray, mirror: dict) -> tuple[list[dict], str]:
    """``prism`` (:func:`hostlink.calibration.report.principal_point_prism`) with the fit started from
    :func:`mirrored_principal_point` (``mirror``: its ``theta``, ``rms_px``, ``n_stars``, ``converged`` and this fit's
    ``rms_px``, ``n_stars``) added to each item, and the one sentence that reports it. ``sigma``: this fit's 1-sigma of
    the model vector."""
    t2 = mirror["theta"]
    apart = np.abs(t2[1:3] - theta[1:3]) / np.maximum(sigma[1:3], 1e-300)
    record = {
        "principal_point_px": [float(t2[1]), float(t2[2])],
        "sigmas_apart": [float(apart[0]), float(apart[1])],
        "rms_px": float(mirror["rms_px"]),
        "n_stars": int(mirror["n_stars"]),
        "converged": bool(mirror["converged"]),
    }
    if np.all(apart < MIRROR_SAME_SIGMAS):
        message = (
            f"a fit started from the mirrored principal point returns to this one ({apart[0]:.2g} and "
            f"{apart[1]:.2g} sigma away in x0 and y0): no second minimum was found there"
        )
        return [{**item, "mirror": record} for item in prism], message
    message = (
        f"a fit started from the mirrored principal point ends at ({t2[1]:.1f}, {t2[2]:.1f}) px, "
        f"{apart[0]:.3g} and {apart[1]:.3g} sigma from this one in x0 and y0, with residual RMS "
        f"{mirror['rms_px']:.4f} px on {mirror['n_stars']} stars against {mirror['this_rms_px']:.4f} px on "
        f"{mirror['this_n_stars']} here" + ("" if mirror["converged"] else " (that fit did not converge)")
    )
    return [{**item, "mirror": record} for item in prism], message


def with_mirror(
    source: ChunkSource,
    nominal: CameraParams,
    res: ChunkedBundleResult,
    options: BundleOptions,
    voted: np.ndarray,
    run_pass: PassRunner,
) -> dict:
    """The degeneracies of the fit ``res``; when its principal point is left to second-order terms with decentering
    and prism free (:func:`hostlink.calibration.report.principal_point_prism`), the same fit (same parameters, same
    weights: ``source`` is the floored one) started from the mirrored principal point
    (:func:`mirrored_principal_point`) is run and reported beside it, so the user sees
    the other minimum rather than a 1-sigma that only describes this one (docs/calibration.md).
    ``options.mirror_fit`` False: the degeneracies alone, without that second fit (a report only: the camera is this
    fit's either way)."""
    deg = degeneracies(res.normal, res.estimate, res.normal_u_diag)
    prism = deg["principal_point_prism"]
    if not prism or not options.mirror_fit:
        return deg
    sigma = np.sqrt(np.abs(np.diag(full_covariance(res))))
    mirrored = mirrored_principal_point(res.theta, prism)
    if not mirror_is_distinct(res.theta, mirrored, sigma):
        message = "the mirrored principal point is this one (its decentering equals its prism, p = s): no second fit"
        return {**deg, "messages": [*deg["messages"], message]}
    start = nominal.with_model_vector(mirrored)
    other = bundle_adjust_chunks(source, start, replace(options, estimate=res.estimate), voted, run_pass, ())
    mirror = {
        "theta": other.theta,
        "rms_px": stats_from_sums(other.residual_sums)["rms_px"],
        "n_stars": other.n_obs,
        "converged": other.converged,
        "this_rms_px": stats_from_sums(res.residual_sums)["rms_px"],
        "this_n_stars": res.n_obs,
    }
    items, message = mirror_report(prism, res.theta, sigma, mirror)
    return {**deg, "principal_point_prism": items, "messages": [*deg["messages"], message]}


def full_covariance(res: ChunkedBundleResult) -> np.ndarray:
    """The (10, 10) covariance of the model vector, zero for the parameters not estimated."""
    cov = np.zeros((10, 10), dtype=np.float64)
    idx = [ESTIMATE_NAMES.index(n) for n in res.estimate]
    cov[np.ix_(idx, idx)] = res.covariance
    return cov
