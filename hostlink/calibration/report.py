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

from hostlink.calibration.data import (
    CalibrationData,
    block_gram,
    count_blocks,
    half_angle_from_dot_rad,
)
from hostlink.calibration.frames import wahba_attitudes
from hostlink.calibration.model import (
    DEFAULT_CHUNK_OBS,
    angle_arcsec,
    half_diagonal_px,
    observation_residuals,
    residuals,
    rotate,
)
from onboard.camera import pixels_to_unit
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Correlations beyond this are reported as degeneracies.
CORRELATION_LIMIT = 0.95
#: Fraction of a parameter's information taken by the attitudes beyond which it is reported as traded off.
ATTITUDE_LIMIT = 0.95
#: Each principal-point coordinate with the decentering and thin-prism coefficients that cancel its shift to first
#: order (:func:`hostlink.calibration.mirror.prism_shift_direction`).
PRINCIPAL_POINT_PRISM = (("x0", "p1", "s1"), ("y0", "p2", "s2"))


def fitted_attitudes(data: CalibrationData, theta: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Per-frame least-squares attitude for a camera (:func:`hostlink.calibration.frames.wahba_attitudes`; methods
    without attitudes of their own, and the 'before' state).
    ``b``: the stars' measured directions at ``theta`` when already computed."""
    b = pixels_to_unit(data.x_px, data.y_px, theta) if b is None else b
    return wahba_attitudes(b, data.r, data.frame_starts)


def residual_stats(data: CalibrationData, theta: np.ndarray, attitudes: np.ndarray) -> dict:
    """RMS and maximum residual in measured px and in arcsec (see module docstring)."""
    e = residuals(data, theta, attitudes)
    e_len = np.linalg.norm(e, axis=1)
    stats = stats_from_sums(residual_sums(data, theta, attitudes, e_len))
    stats["rms_px_clipped"] = clipped_rms(e_len)
    return stats


def residual_sums(
    data: CalibrationData,
    theta: np.ndarray,
    attitudes: np.ndarray,
    e_len: np.ndarray | None = None,
    b: np.ndarray | None = None,
) -> dict:
    """The additive parts of :func:`residual_stats` (sums of squares, maxima, counts), so chunks of frames combine
    exactly (:func:`merge_sums`, then :func:`stats_from_sums`). ``e_len``, ``b``: the residual lengths and the
    measured directions at ``theta`` when already computed."""
    att_obs = np.repeat(attitudes, data.counts, axis=0)
    s = rotate(att_obs, data.r)  # C r: for the angles and, when not given, the residuals
    if e_len is None:
        e_len = np.linalg.norm(observation_residuals(data.x_px, data.y_px, data.r, att_obs, theta, s), axis=1)
    b = pixels_to_unit(data.x_px, data.y_px, theta) if b is None else b
    ang = angle_arcsec(b, s)
    return {
        "sum_px2": float(np.sum(e_len**2)),
        "max_px": float(np.max(e_len, initial=0.0)),
        "sum_arcsec2": float(np.sum(ang**2)),
        "max_arcsec": float(np.max(ang, initial=0.0)),
        "n_stars": int(data.n_obs),
        "n_frames": int(data.n_frames),
    }


def merge_sums(a: dict, b: dict) -> dict:
    """Two :func:`residual_sums` (or interstar sums) combined: sums add, maxima take the larger."""
    return {k: max(a[k], b[k]) if k.startswith("max") else a[k] + b[k] for k in a}


def stats_from_sums(sums: dict) -> dict:
    """:func:`residual_stats` from merged :func:`residual_sums` (no clipped RMS: it needs every residual)."""
    n = max(sums["n_stars"], 1)
    return {
        "rms_px": float(np.sqrt(sums["sum_px2"] / n)),
        "max_px": sums["max_px"],
        "rms_arcsec": float(np.sqrt(sums["sum_arcsec2"] / n)),
        "max_arcsec": sums["max_arcsec"],
        "n_stars": sums["n_stars"],
        "n_frames": sums["n_frames"],
        "rms_px_clipped": None,
    }


def clipped_rms(e_len: np.ndarray, k: float = 3.0, max_passes: int = 20) -> float:
    """RMS [px] of the residual lengths left after iterative k-sigma clipping (drop |e| > k x RMS of the kept ones,
    repeat until nothing more is dropped): the figure other calibration tools report as their residual, for a
    comparison on the same footing."""
    keep = np.ones(e_len.shape, dtype=bool)
    for _ in range(max_passes):
        rms = float(np.sqrt(np.mean(e_len[keep] ** 2))) if keep.any() else float("nan")
        new_keep = e_len <= k * rms
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return rms


def interstar_rms_rad(data: CalibrationData, theta: np.ndarray, chunk_obs: int = DEFAULT_CHUNK_OBS) -> float:
    """Seed 000's Delta_rms [rad] over all n(n-1)/2 pairs of every frame (in blocks of frames, bounded memory)."""
    total, count = interstar_sums(data, theta, chunk_obs)
    return math.sqrt(total / count) if count else float("nan")


def interstar_sums(data: CalibrationData, theta: np.ndarray, chunk_obs: int = DEFAULT_CHUNK_OBS) -> tuple[float, int]:
    """(sum of squared interstar angle differences [rad^2], number of pairs) of :func:`interstar_rms_rad`."""
    return interstar_sums_at(data, [theta], chunk_obs)[0]


def interstar_sums_at(
    data: CalibrationData, thetas: list[np.ndarray], chunk_obs: int = DEFAULT_CHUNK_OBS
) -> list[tuple[float, int]]:
    """:func:`interstar_sums` for each camera of ``thetas``, the catalogue angles computed once
    (:func:`interstar_sums_of_directions` of the stars' directions through each camera)."""
    return interstar_sums_of_directions(data, [pixels_to_unit(data.x_px, data.y_px, th) for th in thetas], chunk_obs)


def interstar_sums_of_directions(
    data: CalibrationData, bs: list[np.ndarray], chunk_obs: int = DEFAULT_CHUNK_OBS
) -> list[tuple[float, int]]:
    """:func:`interstar_sums` for each array of measured directions (N, 3) in ``bs``, the catalogue angles computed
    once. The frames go in blocks of one star count n (:func:`hostlink.calibration.data.count_blocks`, at most
    ``chunk_obs`` stars), each block's directions an (m, n, 3) stack whose Gram matrices hold every pair's dot
    product, without padding; the pairs i < j are the same entries of each (one gather along the rows). Each
    difference is that of the half angles (:func:`hostlink.calibration.data.half_angle_from_dot_rad`), doubled in
    the sum: the same numbers as the angles' (scalings by two are exact)."""
    out = [(0.0, 0) for _ in bs]
    for rows, m, n in count_blocks(data.frame_starts, chunk_obs):
        if n < 2:
            continue
        first, second = np.triu_indices(n, 1)
        upper = first * n + second  # pairs i < j in an n x n matrix
        half_r = half_angle_from_dot_rad(np.take(block_gram(data.r, rows, m, n), upper, axis=1))
        for k, b in enumerate(bs):
            d = half_angle_from_dot_rad(np.take(block_gram(b, rows, m, n), upper, axis=1))
            d -= half_r
            out[k] = (out[k][0] + 4.0 * float(np.vdot(d, d)), out[k][1] + d.size)
    return out


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
    - ``principal_point_prism``: each principal-point coordinate traded off against attitude and correlated beyond
      :data:`CORRELATION_LIMIT` with its decentering or thin-prism coefficient (:func:`principal_point_prism`).
    - ``principal_point_prism``: each principal-point coordinate traded off against attitude and correlated beyond
      :data:`CORRELATION_LIMIT` with its decentering or thin-prism coefficient (:func:`principal_point_prism`).
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
    prism: list[dict] = []
    if u_diag is not None:
        lost = 1.0 - np.diag(normal) / np.maximum(u_diag, 1e-300)
        for i, name in enumerate(estimate):
            if lost[i] > ATTITUDE_LIMIT:
                tradeoff.append({"parameter": name, "information_absorbed_by_attitude": float(lost[i])})
                messages.append(
                    f"{name} trades off against attitude: the per-frame attitudes absorb {100 * lost[i]:.6g} % of "
                    f"the information on it, and the remaining {100 * (1 - lost[i]):.2g} % is what sets its 1-sigma "
                    "above (only the perspective across the field tells them apart: more frames or a wider field "
                    "shrink it)"
                )
        prism = principal_point_prism(tradeoff, correlated, tuple(estimate))
        messages.extend(p["message"] for p in prism)
    return {
        "condition_number": cond,
        "correlated": correlated,
        "weak_directions": weak,
        "attitude_tradeoff": tradeoff,
        "principal_point_prism": prism,
        "messages": messages,
    }


def principal_point_prism(
    tradeoff: list[dict], correlated: list[dict], estimate: tuple[str, ...] | None = None
) -> list[dict]:
    """The principal-point coordinates the data leave to terms of second order
    (:func:`hostlink.calibration.mirror.prism_shift_direction`): traded off against attitude (``tradeoff`` of
    :func:`degeneracies`) and correlated beyond :data:`CORRELATION_LIMIT` with their decentering or thin-prism
    coefficient (``correlated``). Their linearised 1-sigma is that of the local minimum only: the cost along the shift
    is set by second-order terms and can have another minimum with the shift reversed (docs/calibration.md, "Principal
    point with decentering and prism free").

    The shift moves no star to first order only with both coefficients free: with ``estimate`` given, a coordinate
    whose decentering or prism coefficient is held is not listed (with p1 alone the shift leaves d r^2 / (2 F^2) in x,
    first order in d, so x0 is determined and its 1-sigma is the spread of fits even at a correlation of 0.977 with p1:
    docs/calibration.md, "Off-centre strip: the principal point's stated 1-sigma")."""
    traded = {t["parameter"] for t in tradeoff}
    pairs = {frozenset((c["a"], c["b"])): c["rho"] for c in correlated}
    out = []
    for pp, p, s in PRINCIPAL_POINT_PRISM:
        if estimate is not None and not (p in estimate and s in estimate):
            continue
        rho = {n: pairs[frozenset((pp, n))] for n in (p, s) if frozenset((pp, n)) in pairs}
        if pp not in traded or not rho:
            continue
        worst = max(rho, key=lambda n: abs(rho[n]))
        message = (
            f"{pp} is not determined with {p} and {s} free: shifting the principal point by d px with {p} and -{s} "
            f"each grown by d / (2 F^2) moves no star to first order once the attitudes are re-fitted ({pp} and "
            f"{worst}: rho = {rho[worst]:+.3f}), so the cost along that shift is set by second-order terms and can "
            "have another minimum with the shift reversed: the 1-sigma above is that of this minimum only. Hold "
            "decentering and prism (--estimate f,x0,y0,k1,k2,k3), or the thin prism alone (--estimate "
            "f,x0,y0,k1,k2,k3,p1,p2), or the principal point, or add frames with a wider field"
        )
        out.append({"parameter": pp, "with": [p, s], "rho": rho, "message": message})
    return out


def principal_point_prism_note(prism: list[dict]) -> str | None:
    """One line for a summary (the bench's calibration phase) when :func:`principal_point_prism` found coordinates
    the data leave to second-order terms, else None: their stated 1-sigma is that of the fit's own minimum, below the
    spread of fits and the Cramer-Rao bound at the truth when the truth lies near the prism-free point
    (docs/calibration.md, "Off-centre strip: the principal point's stated 1-sigma")."""
    if not prism:
        return None
    names = ", ".join(p["parameter"] for p in prism)
    with_names = {m for p in prism for m in p["with"]}
    without = ",".join(n for n in ESTIMATE_NAMES if n not in with_names)
    without_prism = ",".join(n for n in ESTIMATE_NAMES if n not in with_names or not n.startswith("s"))
    return (
        f"{names} not determined with decentering and prism free: the 1-sigma is that of this minimum only "
        f"(if the lens has none, hold them, --estimate {without}, or the thin prism, --estimate {without_prism})"
    )


#: Auto-hold (:func:`undetermined_parameters`): the principal point is held at nominal when its 1-sigma exceeds this
#: fraction of the detector half-diagonal (7 px on a 1024 x 1024 detector): the data then say less about it than a
#: nominal at the detector centre does (a detector mounted to ~0.1 mm).
HOLD_PRINCIPAL_POINT_FRACTION = 0.01
#: Auto-hold: a distortion coefficient is held at nominal when a 1-sigma change of it moves a star at the detector
#: half-diagonal by more than this [px]: the data cannot tell the distortion from no distortion at that level.
HOLD_DISTORTION_PX = 1.0
#: Auto-hold: a held parameter (pair) is released when freeing it lowers the cost by more than this: chi-square with 1
#: and 2 degrees of freedom at the 5-sigma tail probability 5.7e-7 (scipy.stats.chi2.isf(2 * norm.sf(5), k)). So
#: strict because a few frames of a narrow field put the free principal point 3 of its sigmas from the truth more
#: often than a Gaussian would (a flat, curved valley of the cost): 99 % (9.2) released it in 2 of 8 five-frame trials.
RELEASE_LIMIT = {1: 25.0, 2: 28.74}


def _hold_limits_px(params: CameraParams) -> dict[str, float]:
    half_diag = half_diagonal_px(params)
    limits = {n: HOLD_DISTORTION_PX for n in ESTIMATE_NAMES[3:]}
    limits.update({"f": math.inf, "x0": HOLD_PRINCIPAL_POINT_FRACTION * half_diag})
    limits["y0"] = limits["x0"]
    return limits


def _held_cost(normal: np.ndarray, offset: np.ndarray, hold: np.ndarray) -> float:
    """Rise of the quadratic model of the fit's cost (unit noise) when the parameters ``hold`` (bool mask) are moved
    by ``offset`` (nominal - estimate, model-vector units) and the others re-fitted: d_h^T (S_hh - S_hk S_kk^-1 S_kh)
    d_h (the Schur complement of the kept block)."""
    from hostlink.calibration.normal import covariance_from_normal

    if not np.any(hold):
        return 0.0
    keep = ~hold
    s_hh = normal[np.ix_(hold, hold)]
    if np.any(keep):
        s_hk = normal[np.ix_(hold, keep)]
        s_hh = s_hh - s_hk @ covariance_from_normal(normal[np.ix_(keep, keep)], 1.0) @ s_hk.T
    d = offset[hold]
    return float(d @ s_hh @ d)


def undetermined_parameters(
    normal: np.ndarray,
    estimate: tuple[str, ...],
    sigma_px: float,
    params: CameraParams,
    theta_fit: np.ndarray,
) -> tuple[tuple[str, ...], list[dict]]:
    """The parameters the data determine, and those to hold at nominal with the reason, from the information.

    ``normal``: the camera block S of the information (attitudes eliminated, unit noise, model-vector units) of a
    fit of ``estimate`` whose result is ``theta_fit`` (full model vector); ``sigma_px``: centroid noise per axis;
    ``params``: the nominal (the values held).

    1. Not determined: a parameter's 1-sigma with every other remaining parameter free (sigma^2 S^-1), expressed as
       its effect [px] at the detector half-diagonal (``bundle.parameter_scales``), above its limit
       (:data:`HOLD_PRINCIPAL_POINT_FRACTION`, :data:`HOLD_DISTORTION_PX`; the focal length is never held). The
       worst against its limit is held (the principal point as a pair), the rest are taken again without it, until
       every remaining one is within its limit. A direction with no information at all is held first.
    2. Unless the data contradict the nominal: a held group is released (estimated) when freeing it, with the other
       held parameters at nominal, lowers the cost by more than 5-sigma evidence allows (:data:`RELEASE_LIMIT`;
       the likelihood-ratio test, from the quadratic model of the fit: :func:`_held_cost`). A parameter that the data
       place far from its nominal, however loosely, is estimated (an off-centre detector)."""
    from hostlink.calibration.model import parameter_scales
    from hostlink.calibration.normal import covariance_from_normal

    limits = _hold_limits_px(params)
    scales = dict(zip(ESTIMATE_NAMES, parameter_scales(params), strict=True))
    cols = [ESTIMATE_NAMES.index(n) for n in estimate]
    offset = params.model_vector(np.float64)[cols] - np.asarray(theta_fit, dtype=np.float64)[cols]
    keep = list(estimate)
    groups: list[tuple[list[str], dict[str, float]]] = []
    while True:
        idx = [estimate.index(n) for n in keep]
        cov = covariance_from_normal(normal[np.ix_(idx, idx)], sigma_px)
        sd = np.sqrt(np.abs(np.diag(cov)))
        effect = {n: float(sd[k] / scales[n]) for k, n in enumerate(keep)}
        worst = max(keep, key=lambda n: effect[n] / limits[n]) if keep else None
        if worst is None or not effect[worst] > limits[worst]:
            break
        group = [n for n in ("x0", "y0") if n in keep] if worst in ("x0", "y0") else [worst]
        groups.append((group, {n: effect[n] for n in group}))
        keep = [n for n in keep if n not in group]
    hold = np.array([n not in keep for n in estimate])
    lr_of = {}
    released = True
    while released:
        released = False
        for group, _ in groups:
            g = np.array([n in group for n in estimate])
            if not np.any(hold & g):
                continue
            lr = (_held_cost(normal, offset, hold) - _held_cost(normal, offset, hold & ~g)) / sigma_px**2
            lr_of[group[0]] = lr
            if lr > RELEASE_LIMIT[len(group)]:
                hold &= ~g
                released = True
    held = []
    for group, effect in groups:
        if not hold[estimate.index(group[0])]:
            continue
        lr = lr_of[group[0]]
        for n in group:
            what = "px" if n in ("x0", "y0") else "px at the detector half-diagonal"
            reason = (
                "not determined by the data (no information)"
                if not math.isfinite(effect[n])
                else f"1-sigma {effect[n]:.3g} {what} > limit {limits[n]:.3g} px; the data do not contradict the "
                f"nominal (likelihood ratio {lr:.2g} < {RELEASE_LIMIT[len(group)]:.3g})"
            )
            held.append({"parameter": n, "sigma_effect_px": effect[n], "limit_px": limits[n], "reason": reason})
    return tuple(n for n, h in zip(estimate, hold, strict=True) if not h), held


def iterations_text(history: list[dict]) -> str:
    """The iteration count as the live lines number them (the last one printed), and how many of them are the
    evaluated steps plotted in convergence.png (an iteration that ends a stage with a tiny step is not evaluated)."""
    if not history:
        return "0 iterations"
    last = max(int(h["iteration"]) for h in history)
    return f"{last} iterations ({len(history)} evaluated steps)" if last != len(history) else f"{last} iterations"
