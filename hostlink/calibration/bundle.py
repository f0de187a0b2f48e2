"""The default calibration: a bundle adjustment over the camera and the attitude of every frame.

The algorithm, and where each part lives:

- measurement model (:mod:`hostlink.calibration.model`): whitened residuals e = Jc^-1 (q - p) of every star and
  their Jacobians in the camera and the frame's attitude;
- normal equations (:mod:`hostlink.calibration.normal`): U, B, A, g accumulated, the attitudes eliminated by the
  Schur complement S = U - sum_f B_f A_f^-1 B_f^T, the step solved, the covariance sigma^2 S^-1;
- passes over the data (:mod:`hostlink.calibration.passes`, chunks from :mod:`hostlink.calibration.source`): per
  pass the attitudes eliminated at the pass's camera and the reduced sums added up over chunks of frames (memory
  O(K^2 + one chunk)); a final pass also gives the unit-weight matrix, the gate and the sums after gating;
- the Levenberg-Marquardt loop (:func:`hostlink.calibration.lm.lm_round`): one round at a fixed robust scale, with
  named termination tests and the status it stops with;
- this module: the rounds. A least-squares round (on warm-start samples first, when given), then robust rounds
  (Huber weights at the scale of the round before), each ending with a final pass whose stars beyond the gate are
  dropped for the next; the fit ends when no star is gated and the scale has settled.

A dense textbook Gauss-Newton/Levenberg-Marquardt solver of the same problem is kept beside it
(:mod:`hostlink.calibration.reference`): the tests compare the two.

Robustness: interstar voting before the fit, Huber weights during it, gating after it (``robust``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hostlink.calibration.acceleration import ACCELERATION_MAX_RATIO, step_acceleration
from hostlink.calibration.data import CalibrationData, measured_directions
from hostlink.calibration.lm import LMState, RoundResult, RoundSetup, Status, lm_round
from hostlink.calibration.model import (
    ARCSEC_PER_RAD,
    DEFAULT_CHUNK_OBS,
    observation_terms,
    parameter_columns,
    parameter_scales,
    residuals,
)
from hostlink.calibration.normal import (
    NormalBlocks,
    accumulate_normals,
    covariance_from_normal,
    normal_blocks,
    reduced_normal,
    solve_scaled,
    unit_weight_normal,
)
from hostlink.calibration.passes import (
    PassRequest,
    PassRunner,
    PassSums,
    frame_attitudes,
    initial_attitudes,
    robust_sigma_from_histogram,
    serial_pass,
)
from hostlink.calibration.robust import vote_consistent_stars
from hostlink.calibration.source import ChunkSource, in_memory_source, without_rows
from onboard.params import ESTIMATE_NAMES, CameraParams

#: Names other modules and the tests import from here (the parts of the algorithm, re-exported).
__all__ = [
    "ARCSEC_PER_RAD",
    "ACCELERATION_MAX_RATIO",
    "DEFAULT_CHUNK_OBS",
    "BundleOptions",
    "BundleResult",
    "ChunkSource",
    "ChunkedBundleResult",
    "NormalBlocks",
    "PassRequest",
    "accumulate_normals",
    "bundle_adjust",
    "bundle_adjust_chunks",
    "covariance_from_normal",
    "frame_attitudes",
    "initial_attitudes",
    "normal_blocks",
    "observation_terms",
    "parameter_columns",
    "parameter_scales",
    "reduced_normal",
    "residuals",
    "solve_scaled",
    "step_acceleration",
    "unit_weight_normal",
]

#: A robust-scale round ends when the robust sigma of its residuals is within this fraction of the scale its Huber
#: weights used: a 1 % different scale moves the Huber threshold (3 sigma) by 0.03 sigma, which changes the weight
#: of ~0.1 % of the stars slightly and the estimate by far less than 0.01 sigma.
SCALE_ROUND_TOL = 0.01
#: The first round (plain least squares, before any robust scale is known) stops at steps below this many standard
#: deviations: the robust rounds after it continue from there to ``BundleOptions.step_tol``.
ROUGH_STEP_SIGMAS = 0.1
#: A warm-start sample's rounds stop at steps below this many of the sample's own standard deviations: the minimum
#: of the next, ~10x larger level lies ~3 of them away (sampling: the sqrt(10) parameters' share of the frames left
#: out), and what a step of s leaves (~1.5e-3 s^2) is far below that, so converging a sample further only costs
#: passes; the next level's first step absorbs the difference.
WARM_STEP_SIGMAS = 2.0
#: Rounds that may gate stars: a round that gates none ends the gating; the bound only stops data whose tail keeps
#: growing under every gate from costing a round each.
MAX_GATE_ROUNDS = 5
#: Rounds after the gating rounds for the robust scale to settle within :data:`SCALE_ROUND_TOL` (it moves by the
#: share of the gated stars only; one round settles it in the tests' sessions, three bound it).
MAX_SCALE_ROUNDS = 3


@dataclass(frozen=True)
class BundleOptions:
    estimate: tuple[str, ...] = ESTIMATE_NAMES
    max_iter: int = 100
    noise_px: float | None = None  # known centroid noise per axis; None: estimated from the residuals
    huber_k: float = 3.0  # Huber threshold in robust sigmas (efficiency ~99.5 % for Gaussian noise)
    gate: float = 5.0  # residuals beyond this many robust sigmas are dropped (2-D Gaussian: P = 3.7e-6)
    chunk_obs: int = DEFAULT_CHUNK_OBS
    #: stop when the relative cost decrease of an accepted step is below this
    ftol: float = 1e-12
    #: ... or when a step moves the camera by less than this many standard deviations (the step is applied:
    #: Gauss-Newton here shrinks each step ~50-fold, so <= 4e-4 sigma is left; tests/test_calibration_chunked.py
    #: checks 1e-3). 0.02 rather than 0.01: the first step after a few stars are gated is ~0.015 sigma, and it then
    #: ends the round on the gating pass's sums, without a pass of its own
    step_tol: float = 2e-2
    #: ... or when the step times the contraction measured between this fit's steps
    #: (:data:`hostlink.calibration.lm.CONTRACTION_MAX`) is below this many standard deviations: the step is
    #: applied, and what is left of the error is at most that product while the contraction does not grow. 0.005
    #: sigma raises the camera's mean square error by 2.5e-5 of its variance; it saves the pass that would only
    #: confirm a step of ~0.15 sigma
    remainder_tol: float = 5e-3
    progress: Callable[[dict], None] | None = None
    #: after a fit whose principal point is left to its decentering and prism, fit again from the mirrored
    #: principal point and report that second minimum (:func:`hostlink.calibration.mirror.with_mirror`); False for a
    #: caller that only needs the camera (the report's second fit changes no parameter)
    mirror_fit: bool = True


@dataclass
class BundleResult:
    theta: np.ndarray  # model vector (F in px), all 10 entries
    attitudes: np.ndarray  # (M_fit, 3, 3) for the frames of ``data``
    data: CalibrationData  # the rows and frames that were fitted (inliers)
    rows_used: np.ndarray  # (N_input,) bool: input rows kept
    rows_gated: np.ndarray  # (N_input,) bool: input rows dropped by residual gating (the rest of the drops: voting,
    # or a frame left with fewer than three stars)
    n_rejected_voting: int
    n_rejected_gating: int
    n_frames_dropped: int
    sigma_px: float  # centroid noise per axis used for the covariance
    sigma_estimated_px: float  # from the final residuals
    estimate: tuple[str, ...]
    normal: np.ndarray  # (K, K) reduced normal matrix S / 1 (unit noise), model-vector units
    normal_u_diag: np.ndarray  # (K,) diagonal of U before the attitudes are eliminated
    covariance: np.ndarray  # (K, K) sigma^2 S^-1, model-vector units
    history: list[dict] = field(default_factory=list)
    converged: bool = False
    status: Status = Status.MAX_ITER  # why the last round stopped


@dataclass
class ChunkedBundleResult:
    """The camera of :func:`bundle_adjust_chunks` and what the report needs; no per-frame state."""

    theta: np.ndarray
    estimate: tuple[str, ...]
    normal: np.ndarray
    normal_u_diag: np.ndarray
    covariance: np.ndarray
    sigma_px: float
    sigma_estimated_px: float
    robust_sigma_px: float
    gated_rows: np.ndarray  # source rows dropped by residual gating (sorted int64)
    n_obs: int
    n_frames: int
    max_e_px: float
    history: list[dict] = field(default_factory=list)
    converged: bool = False
    #: the residual sums of the final pass (``report.residual_sums``' keys), at the camera of that pass: ``theta``
    #: less the last step, below ``BundleOptions.step_tol`` or ``remainder_tol`` standard deviations
    residual_sums: dict = field(default_factory=dict)
    status: Status = Status.MAX_ITER  # why the last round stopped


@dataclass(frozen=True)
class _Problem:
    """What every round of one fit shares: the data, the estimated columns and their scales, the stars left out
    before the fit, the options, the pass runner and the warm-start samples."""

    source: ChunkSource
    cols: np.ndarray
    scale: np.ndarray
    excluded: np.ndarray
    opt: BundleOptions
    run_pass: PassRunner
    warm_start: tuple[CalibrationData, ...]

    def request(
        self, gated: np.ndarray, theta: np.ndarray, sigma: float, final: bool = False, gate_px: float = np.inf
    ) -> PassRequest:
        """The pass at ``theta`` with Huber weights of scale ``sigma``, the excluded and ``gated`` rows left out."""
        drop = np.union1d(self.excluded, gated)
        opt = self.opt
        return PassRequest(theta, sigma, self.cols, self.scale, drop, opt.huber_k, opt.chunk_obs, final, gate_px)

    def run(
        self,
        gated: np.ndarray,
        theta: np.ndarray,
        sigma: float,
        final: bool = False,
        gate_px: float = np.inf,
        first: bool = False,
        src: ChunkSource | None = None,
    ) -> PassSums:
        """A pass over ``src`` (default the full data), checked (:func:`_checked`)."""
        src = self.source if src is None else src
        return _checked(self.run_pass(src, self.request(gated, theta, sigma, final, gate_px)), first)


def _checked(sums: PassSums, first: bool) -> PassSums:
    """``sums``, or ValueError when no frame is left or the cost is not finite (``first``: before any gating)."""
    if sums.n_frames == 0 or not np.isfinite(sums.cost):
        raise ValueError(
            "no frame with at least 3 consistent identified stars"
            if first
            else "every frame lost its stars to outlier gating"
        )
    return sums


def _round_setup(problem: _Problem, gated: np.ndarray, src: ChunkSource, sigma: float, step_tol: float) -> RoundSetup:
    """The :class:`RoundSetup` of a round over ``src`` at the robust scale ``sigma`` (inf: least squares)."""
    opt = problem.opt
    full = src is problem.source

    def evaluate(theta: np.ndarray, final: bool, gate_px: float) -> PassSums:
        return problem.run_pass(src, problem.request(gated, theta, sigma, final, gate_px))

    def accelerate(theta: np.ndarray, dx: np.ndarray, cur: PassSums) -> np.ndarray:
        return _accelerated(problem, gated, theta, dx, cur, sigma)

    return RoundSetup(
        evaluate=evaluate,
        cols=problem.cols,
        col_scale=problem.scale,
        step_tol=step_tol,
        remainder_tol=opt.remainder_tol,
        ftol=opt.ftol,
        max_iter=opt.max_iter,
        damped=not np.isfinite(sigma),
        full_robust=bool(np.isfinite(sigma)) and full,
        gate_sigmas=opt.gate,
        accelerate=accelerate if full and problem.warm_start else None,
        progress=opt.progress,
    )


def _accelerated(
    problem: _Problem, gated: np.ndarray, theta: np.ndarray, dx: np.ndarray, cur: PassSums, sigma: float
) -> np.ndarray:
    """``dx`` plus half its geodesic acceleration (:func:`step_acceleration`, measured on the first warm-start
    level less the stars left out), when Transtrum and Sethna's bound admits it."""
    sample = without_rows(problem.warm_start[0], np.union1d(problem.excluded, gated))
    if sample.n_frames == 0:
        return dx
    opt = problem.opt
    accel = step_acceleration(sample, theta, dx, problem.cols, problem.scale, sigma, opt.huber_k, cur.s, cur.n_obs)
    if accel is None:
        return dx
    size = np.sqrt(max(accel @ cur.s @ accel, 0.0) / max(dx @ cur.s @ dx, 1e-300))
    return dx + 0.5 * accel if 2.0 * size <= ACCELERATION_MAX_RATIO else dx


def _warm_start(problem: _Problem, theta: np.ndarray, state: LMState) -> tuple[np.ndarray, float]:
    """The least-squares round on each warm-start sample in turn (coarse to fine; the later ones at the scale of
    the one before) to :data:`WARM_STEP_SIGMAS`: the camera and robust scale the full data start from."""
    sigma = np.inf
    none = np.zeros(0, dtype=np.int64)
    for level in problem.warm_start:
        warm = in_memory_source(level)
        cur = problem.run(none, theta, sigma, first=True, src=warm)
        res = lm_round(_round_setup(problem, none, warm, sigma, WARM_STEP_SIGMAS), theta, cur, state)
        theta, sigma = res.theta, robust_sigma_from_histogram(res.last.hist)
    return theta, sigma


@dataclass
class _Rounds:
    """Where the robust rounds stopped: the camera, the final pass and the rows gated so far."""

    theta: np.ndarray
    final: PassSums
    gated: np.ndarray
    status: Status


def _final_pass(
    problem: _Problem, gated: np.ndarray, res: RoundResult, sigma: float
) -> tuple[PassSums, np.ndarray, float]:
    """The round's final pass, its camera and scale: the round's last pass when it was asked for the final sums (at
    the round's scale), else a pass of its own at the camera reached and the scale of its last pass."""
    if res.last.s_unit is not None:
        return res.last, res.theta_last, sigma
    sigma_new = robust_sigma_from_histogram(res.last.hist)
    return problem.run(gated, res.theta, sigma_new, True, problem.opt.gate * sigma_new), res.theta, sigma_new


def _robust_rounds(problem: _Problem, theta: np.ndarray, sigma: float, state: LMState) -> _Rounds:
    """Rounds from the camera ``theta`` at the scale ``sigma`` (inf: the least-squares round first, to
    :data:`ROUGH_STEP_SIGMAS`). After each, the stars beyond the gate of its final pass are dropped and the next
    round starts from that pass's sums without them (:attr:`hostlink.calibration.passes.PassSums.regated`, no pass
    of its own); when none is, the fit ends once the scale has settled within :data:`SCALE_ROUND_TOL`."""
    opt = problem.opt
    gated = np.zeros(0, dtype=np.int64)
    cur = problem.run(gated, theta, sigma, first=True)
    for round_index in range(MAX_GATE_ROUNDS + MAX_SCALE_ROUNDS):
        step_tol = opt.step_tol if np.isfinite(sigma) else ROUGH_STEP_SIGMAS
        res = lm_round(_round_setup(problem, gated, problem.source, sigma, step_tol), theta, cur, state)
        theta = res.theta
        sigma_new = robust_sigma_from_histogram(res.last.hist)
        final, final_theta, final_scale = _final_pass(problem, gated, res, sigma)
        newly = np.setdiff1d(final.over_gate, gated)
        if newly.size and round_index < MAX_GATE_ROUNDS:
            gated = np.union1d(gated, newly)
            again = final.regated
            cur = _checked(again, False) if again is not None else problem.run(gated, final_theta, final_scale)
            theta, sigma = final_theta, final_scale
            continue
        settled = np.isfinite(sigma) and abs(sigma_new / sigma - 1.0) <= SCALE_ROUND_TOL
        if settled or not res.converged or state.iteration >= opt.max_iter:
            break
        # the next round at the new scale starts from the final pass when it was made at that scale
        cur = final if final_scale == sigma_new else problem.run(gated, theta, sigma_new)
        sigma = sigma_new
    return _Rounds(theta, final, gated, res.status)


def bundle_adjust_chunks(
    source: ChunkSource,
    nominal: CameraParams,
    options: BundleOptions | None = None,
    excluded_rows: np.ndarray | None = None,
    run_pass: PassRunner = serial_pass,
    warm_start: tuple[CalibrationData, ...] = (),
) -> ChunkedBundleResult:
    """Calibrate the camera over the chunks of ``source``, leaving out the stars whose source rows are in
    ``excluded_rows`` (interstar voting's rejects), with one pass over the chunks per Levenberg-Marquardt
    iteration: memory O(K^2 + one chunk) for any number of frames.

    Each pass eliminates every frame's attitude at the pass's camera and sums the reduced normal equations (Schur
    complement) with Huber weights of a fixed robust scale (:mod:`hostlink.calibration.passes`). The first round is
    plain least squares (:func:`_warm_start` on ``warm_start``'s samples of the frames held in memory, coarse to
    fine, when given, so the full data start within a few of their own standard deviations), then the robust rounds
    of :func:`_robust_rounds`, each a :func:`hostlink.calibration.lm.lm_round`. A step of the full data above
    :data:`hostlink.calibration.acceleration.ACCELERATION_MIN_SIGMAS` is taken with its geodesic acceleration
    (on the first warm-start level), so that what the principal point's nonlinearity leaves does not cost a pass
    (pass counts: docs/calibration.md). Raises ValueError when no frame with three stars is left."""
    opt = options or BundleOptions()
    cols = parameter_columns(opt.estimate)
    if cols.size == 0:
        raise ValueError("no parameter to estimate")
    excluded = np.unique(np.asarray(excluded_rows if excluded_rows is not None else [], dtype=np.int64))
    problem = _Problem(source, cols, parameter_scales(nominal)[cols], excluded, opt, run_pass, warm_start)
    state = LMState()
    theta, sigma = _warm_start(problem, nominal.model_vector(np.float64), state)
    rounds = _robust_rounds(problem, theta, sigma, state)
    return _chunked_result(problem, rounds, state)


def _chunked_result(problem: _Problem, rounds: _Rounds, state: LMState) -> ChunkedBundleResult:
    """The result of the rounds: the covariance from the final pass's unit-weight matrix, scaled by the given noise
    or by the one the residuals estimate (degrees of freedom: 2 per star less K and 3 per frame)."""
    final, cols = rounds.final, problem.cols
    dof = max(2 * final.n_obs - cols.size - 3 * final.n_frames, 1)
    sigma_est = float(np.sqrt(final.sum_z2 / dof))  # px, or the scale of the given per-star noise
    sigma_used = float(problem.opt.noise_px) if problem.opt.noise_px else sigma_est
    return ChunkedBundleResult(
        theta=rounds.theta,
        estimate=tuple(ESTIMATE_NAMES[c] for c in cols),
        normal=final.s_unit,
        normal_u_diag=final.u_diag_unit,
        covariance=covariance_from_normal(final.s_unit, sigma_used),
        sigma_px=sigma_used,
        sigma_estimated_px=sigma_est,
        robust_sigma_px=robust_sigma_from_histogram(final.hist),
        gated_rows=rounds.gated,
        n_obs=final.n_obs,
        n_frames=final.n_frames,
        max_e_px=final.max_e_px,
        history=state.history,
        converged=rounds.status.converged,
        residual_sums={
            "sum_px2": final.sum_e2,
            "max_px": final.max_e_px,
            "sum_arcsec2": final.sum_arcsec2,
            "max_arcsec": final.max_arcsec,
            "n_stars": final.n_obs,
            "n_frames": final.n_frames,
        },
        status=rounds.status,
    )


def bundle_adjust(
    data: CalibrationData, nominal: CameraParams, options: BundleOptions | None = None, screen: bool = True
) -> BundleResult:
    """Calibrate the camera and every frame's attitude by robust Levenberg-Marquardt: :func:`bundle_adjust_chunks`
    on ``data`` as one chunk (with interstar voting first when ``screen``), plus the in-memory extras: the inlier
    data, their attitudes and the masks of input rows used and gated.

    ``nominal`` gives the starting values and the fixed values of parameters not in ``options.estimate``.
    Raises ValueError if fewer than one frame with three consistent stars remains.
    """
    opt = options or BundleOptions()
    theta0 = nominal.model_vector(np.float64)
    rows = data.source_rows()
    n_input = data.n_obs
    voted = np.zeros(n_input, dtype=bool)
    if screen:
        voted = ~vote_consistent_stars(data, measured_directions(data, theta0))
    res = bundle_adjust_chunks(in_memory_source(data), nominal, opt, rows[voted])
    rows_gated = np.isin(rows, res.gated_rows)
    fit, rows_used, _ = data.select(~voted & ~rows_gated)
    m_in = data.select(np.ones(n_input, dtype=bool))[0].n_frames
    return BundleResult(
        theta=res.theta,
        attitudes=frame_attitudes(fit, res.theta, res.robust_sigma_px, opt.huber_k),
        data=fit,
        rows_used=rows_used,
        rows_gated=rows_gated,
        n_rejected_voting=int(voted.sum()),
        n_rejected_gating=int(rows_gated.sum()),
        n_frames_dropped=int(m_in - fit.n_frames),
        sigma_px=res.sigma_px,
        sigma_estimated_px=res.sigma_estimated_px,
        estimate=res.estimate,
        normal=res.normal,
        normal_u_diag=res.normal_u_diag,
        covariance=res.covariance,
        history=res.history,
        converged=res.converged,
        status=res.status,
    )
