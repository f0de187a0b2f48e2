"""Calibration statistics, degeneracies and the result file's extras.

Residual statistics (before = nominal camera, after = calibrated camera; both with per-frame attitudes fitted):
- px: the whitened centroid residual of ``bundle.observation_terms``, reported as the RMS and maximum of its length;
- arcsec: the angle between the measured direction b = camera(x, y) and the attitude-rotated reference C r.
Interstar RMS (seed 000 sec. 4.2, Table 1 Delta_rms): RMS over every star pair of every frame of the difference
between the measured and the catalogue interstar angle [rad].
"""

from __future__ import annotations

import math

import numpy as np

from hostlink.calibration.bundle import residuals
from hostlink.calibration.data import CalibrationData, frame_chunks, padded_frames, pair_angles_rad
from hostlink.calibration.frames import wahba_svd
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams

ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi
#: Correlations beyond this are reported as degeneracies.
CORRELATION_LIMIT = 0.95
#: Fraction of a parameter's information taken by the attitudes beyond which it is reported as traded off.
ATTITUDE_LIMIT = 0.95


def fitted_attitudes(data: CalibrationData, theta: np.ndarray) -> np.ndarray:
    """Per-frame SVD attitude for a camera (methods without attitudes of their own, and the 'before' state)."""
    return wahba_svd(pixels_to_unit(data.x_px, data.y_px, theta), data.r, data.frame_starts)


def residual_stats(data: CalibrationData, theta: np.ndarray, attitudes: np.ndarray) -> dict:
    """RMS and maximum residual in measured px and in arcsec (see module docstring)."""
    e = residuals(data, theta, attitudes)
    e_len = np.linalg.norm(e, axis=1)
    b = pixels_to_unit(data.x_px, data.y_px, theta)
    s = np.einsum("nij,nj->ni", np.repeat(attitudes, data.counts, axis=0), data.r)
    ang = 2.0 * np.arcsin(np.clip(np.linalg.norm(b - s, axis=1) / 2.0, 0.0, 1.0)) * ARCSEC_PER_RAD
    return {
        "rms_px": float(np.sqrt(np.mean(e_len**2))),
        "max_px": float(np.max(e_len)),
        "rms_arcsec": float(np.sqrt(np.mean(ang**2))),
        "max_arcsec": float(np.max(ang)),
        "n_stars": int(data.n_obs),
        "n_frames": int(data.n_frames),
    }


def interstar_rms_rad(data: CalibrationData, theta: np.ndarray, chunk_obs: int = 20_000) -> float:
    """Seed 000's Delta_rms [rad] over all n(n-1)/2 pairs of every frame (padded per chunk, bounded memory)."""
    b_all = pixels_to_unit(data.x_px, data.y_px, theta)
    total, count = 0.0, 0
    starts = data.frame_starts
    for f0, f1 in frame_chunks(starts, chunk_obs):
        pf = padded_frames(data, b_all, f0, f1)
        nmax = pf.valid.shape[1]
        upper = np.triu(np.ones((nmax, nmax), dtype=bool), 1)[None] & pf.valid[:, :, None] & pf.valid[:, None, :]
        d = (pair_angles_rad(pf.b) - pair_angles_rad(pf.r))[upper]
        total += float(np.sum(d * d))
        count += d.size
    return math.sqrt(total / count) if count else float("nan")


def sigma_dict(estimate: tuple[str, ...], covariance: np.ndarray, params: CameraParams) -> dict:
    """1-sigma per parameter with the parameter file's key names (f in mm); fixed parameters are 0.0 and listed
    in ``fixed``; a parameter without information is null (JSON) with its name in ``unobservable``."""
    sig = {n: 0.0 for n in ESTIMATE_NAMES}
    unobservable = []
    diag = np.diag(covariance)
    for k, name in enumerate(estimate):
        v = float(diag[k])
        value = math.sqrt(v) if math.isfinite(v) and v >= 0 else None
        if value is not None and name == "f":
            value *= params.pixel_pitch_um / 1000.0
        if value is None:
            unobservable.append(name)
        sig[name] = value
    return {
        "focal_length_mm": sig["f"],
        "principal_point_px": [sig["x0"], sig["y0"]],
        "distortion": {k: sig[k] for k in ESTIMATE_NAMES[3:]},
        "fixed": [n for n in ESTIMATE_NAMES if n not in estimate],
        "unobservable": unobservable,
    }


def degeneracies(normal: np.ndarray, estimate: tuple[str, ...], u_diag: np.ndarray | None = None) -> dict:
    """What the data cannot tell apart, from the (reduced) normal matrix S (information up to sigma^2).

    - ``correlated``: pairs with |rho| > 0.95 in S^-1;
    - ``condition_number`` of the Jacobi-scaled S (the correlation-scale conditioning);
    - ``weak_directions``: eigenvectors of the scaled S whose eigenvalue is below 1e-4 of the largest, given as
      the participating parameters and their weights (the combination the data barely constrain);
    - ``attitude_tradeoff``: with ``u_diag`` (the diagonal before eliminating the attitudes), each parameter whose
      information is more than 95 % absorbed by the per-frame attitudes (e.g. the principal point).
    Every item also appears as one sentence in ``messages``.
    """
    d = np.sqrt(np.maximum(np.diag(normal), 1e-300))
    scaled = normal / d[:, None] / d[None, :]
    vals, vecs = np.linalg.eigh(scaled)
    cond = float(vals[-1] / vals[0]) if vals[0] > 0 else float("inf")
    messages = []
    correlated = []
    try:
        cov = np.linalg.inv(scaled)
        sd = np.sqrt(np.abs(np.diag(cov)))
        rho = cov / sd[:, None] / sd[None, :]
        for a in range(len(estimate)):
            for b in range(a + 1, len(estimate)):
                if abs(rho[a, b]) > CORRELATION_LIMIT:
                    correlated.append({"a": estimate[a], "b": estimate[b], "rho": float(rho[a, b])})
                    messages.append(f"{estimate[a]} and {estimate[b]} are correlated (rho = {rho[a, b]:+.3f})")
    except np.linalg.LinAlgError:
        messages.append("the normal matrix is singular: some parameters are not determined at all")
    weak = []
    for k in np.flatnonzero(vals < 1e-4 * vals[-1]):
        v = vecs[:, k]
        parts = {estimate[i]: float(v[i]) for i in np.argsort(-np.abs(v)) if abs(v[i]) > 0.2}
        weak.append({"eigenvalue_ratio": float(vals[k] / vals[-1]), "combination": parts})
        combo = " ".join(f"{w:+.2f} {n}" for n, w in parts.items())
        messages.append(f"weakly determined combination ({vals[k] / vals[-1]:.1e} of the strongest): {combo}")
    tradeoff = []
    if u_diag is not None:
        lost = 1.0 - np.diag(normal) / np.maximum(u_diag, 1e-300)
        for i, name in enumerate(estimate):
            if lost[i] > ATTITUDE_LIMIT:
                tradeoff.append({"parameter": name, "information_absorbed_by_attitude": float(lost[i])})
                messages.append(
                    f"{name} trades off against attitude ({100 * lost[i]:.4g} % of its information "
                    "is absorbed by the per-frame attitudes)"
                )
    return {
        "condition_number": cond,
        "correlated": correlated,
        "weak_directions": weak,
        "attitude_tradeoff": tradeoff,
        "messages": messages,
    }
