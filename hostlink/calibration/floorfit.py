"""The bundle fit of stars of given sigma_px with the noise floor re-estimated between fits
(:mod:`hostlink.calibration.noisefloor`, :mod:`hostlink.calibration.noisefield`), and its record in the result."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from hostlink.calibration.data import CalibrationData
from hostlink.calibration.noisefield import LR_CRITICAL
from hostlink.calibration.noisefloor import (
    MAX_FLOOR_FITS,
    NoiseComponents,
    NoiseModel,
    NoiseSums,
    field_geometry,
    floor_settled,
    floored_source,
    noise_sums,
    variance_components,
    with_floor,
)
from hostlink.calibration.source import ChunkSource

#: The components are iterated to their own weights until no star's noise moves by more than this share (1 %)
NOISE_SETTLED = 0.01
#: or for at most this many passes over the data (each an attitude fit per frame at the fixed camera).
MAX_NOISE_PASSES = 6
#: ``calibrate(noise_model=...)``: the floor constant or radial as the data choose, or constant only.
NOISE_MODELS = ("auto", "constant")


def fit_with_floor(
    fit: Callable,
    source: ChunkSource,
    nominal,
    start,
    options,
    choose: bool,
    voted: np.ndarray,
    run_pass,
    warm: tuple[CalibrationData, ...],
    radial: bool = True,
) -> tuple[object, list[dict], tuple[NoiseModel, NoiseComponents | None]]:
    """``fit`` (:func:`hostlink.calibration.chunked._fit`, the same arguments) of stars of given sigma_px with the
    noise floor: a fit without a floor, the variance components from its inliers' residuals (constant or radial, as
    the data choose: :func:`~hostlink.calibration.noisefloor.variance_components`), and a fit again with each star's
    noise sqrt(sigma_px^2 + t + t_edge q) (t = floor^2 / scale^2 at the centre, q the squared field radius from the
    nominal principal point over the half-diagonal) until the floor has settled (at most
    :data:`~hostlink.calibration.noisefloor.MAX_FLOOR_FITS` fits; the model choice costs no fit). Returns the last
    fit, its held parameters, and the noise model it weighted with with the last components estimated (None when
    none was: a session fitted once). The warm-start samples are given the same noise. ``radial`` False: the
    constant floor only."""
    noise = field_geometry(nominal)
    comps = None
    for k in range(MAX_FLOOR_FITS):
        src = floored_source(source, noise)
        samples = tuple(with_floor(w, noise) for w in warm)
        res, held = fit(src, nominal, start, options, choose, voted, run_pass, samples)
        if k == MAX_FLOOR_FITS - 1:
            break
        sums, comps, new = settled_components(source, res.theta, np.union1d(voted, res.gated_rows), noise, radial)
        if floor_settled(sums, noise, new):
            break
        noise = new
    return res, held, (noise, comps)


def settled_components(
    source: ChunkSource, theta: np.ndarray, dropped: np.ndarray, noise: NoiseModel, radial: bool
) -> tuple[NoiseSums, NoiseComponents, NoiseModel]:
    """The variance components at the camera ``theta`` iterated to their own weights: estimated from the residuals
    of attitudes weighted by ``noise``, then again from attitudes weighted by the estimate, until the estimate changes
    no star's noise by more than :data:`NOISE_SETTLED` (at most :data:`MAX_NOISE_PASSES` passes over the data, no
    fit of the camera). Iterated, the estimate is the restricted maximum-likelihood one (Koch 1999, sec. 3.6.3:
    the equations hold at the weights of the estimate itself); from the first pass alone, on residuals weighted
    without a floor, a session with a floor from 0.005 px at the centre to 0.4 px at the corner gave b 0.0047 px^2
    (true 2.5e-5), ~13 of its standard errors off. Returns the last sums, the components and their noise model."""
    for _ in range(MAX_NOISE_PASSES):
        sums = noise_sums(source, theta, dropped, noise)
        comps = variance_components(sums, radial)
        new = comps.weights(noise)
        if floor_settled(sums, noise, new, NOISE_SETTLED):
            break
        noise = new
    return sums, comps, new


def radial_allowed(noise_model: str) -> bool:
    """Whether ``noise_model`` (:data:`NOISE_MODELS`) lets the data choose the radial floor; ValueError if unknown."""
    if noise_model not in NOISE_MODELS:
        raise ValueError(f"unknown noise model {noise_model!r} (choose from {', '.join(NOISE_MODELS)})")
    return noise_model == "auto"


def noise_outcome(scale: float, noise: NoiseModel, comps: NoiseComponents | None) -> dict:
    """The outcome's noise fields of a fit of fitted noise ``scale`` weighted by ``noise``: the scale, the floor at
    the centre and at the half-diagonal [px], the model's record and the weights' model."""
    return {
        "noise_scale": scale,
        "noise_floor_px": scale * math.sqrt(noise.t_px2),
        "noise_floor_edge_px": scale * math.sqrt(noise.t_px2 + noise.t_edge_px2),
        "noise_model": noise_model_record(noise, comps),
        "noise_weights": noise,
    }


def noise_model_record(noise: NoiseModel, comps: NoiseComponents | None) -> dict:
    """The result's record of the noise model: which (``constant`` or ``radial``), the floor^2 components b (centre)
    and c (growth to the half-diagonal) [px^2] with their standard errors, the floor at the centre and at the
    half-diagonal [px], the likelihood-ratio statistic against the constant floor and the threshold it was held to
    (:func:`~hostlink.calibration.noisefield.lr_critical`),
    and the field geometry (the nominal principal point and the half-diagonal [px])."""
    record = {"centre_px": list(noise.center_px), "half_diagonal_px": noise.r_max_px, "lr_critical": LR_CRITICAL}
    if comps is None:
        return {"model": "constant", "floor_px2": 0.0, "edge_px2": 0.0, **record}
    record["lr_critical"] = comps.lr_critical
    return {
        "model": comps.model,
        "floor_px2": comps.floor_px**2,
        "floor_sigma_px2": comps.b_sigma_px2,
        "edge_px2": comps.edge_px2,
        "edge_sigma_px2": comps.c_sigma_px2,
        "floor_centre_px": comps.floor_px,
        "floor_edge_px": math.sqrt(comps.floor_px**2 + comps.edge_px2),
        "scale": comps.scale,
        "lr": comps.lr,
        **record,
    }


def noise_model_text(record: dict, radial_tried: bool = True) -> str:
    """One line on the noise model of ``record`` (:func:`noise_model_record`) for the command's report;
    ``radial_tried`` False (``noise_model="constant"``, ``--noise-model constant``): the floor held constant, no
    likelihood ratio to give."""
    if not radial_tried:
        return "noise floor held constant over the field (--noise-model constant)"
    lr = f"likelihood ratio {record.get('lr', 0.0):.1f} against {record['lr_critical']:.2f} to choose the radial one"
    if record["model"] != "radial":
        return f"noise floor constant over the field ({lr})"
    return (
        f"noise floor growing with field radius: floor^2 = {record['floor_px2']:.5f} "
        f"+- {record['floor_sigma_px2']:.5f} + ({record['edge_px2']:.5f} +- {record['edge_sigma_px2']:.5f}) "
        f"(r / {record['half_diagonal_px']:.0f} px)^2 px^2, {record['floor_centre_px']:.4f} px at the centre and "
        f"{record['floor_edge_px']:.4f} px at the corner radius ({lr})"
    )
