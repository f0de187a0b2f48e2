"""The sensor's command and frame state machine: the single authority for what a sensor accepts, on every link.

A :class:`Firmware` takes decoded protocol commands (``handle``) and exposures (``process_frame``) and returns
protocol replies. It owns the parameter banks (``onboard.banks``: staging, verify, A/B commit) and the onboard
recursive estimator, which it restarts from the active set after every commit, with that set's 1-sigma prior
(``onboard.prior``: the sigma the set carries, the cold-start prior where it is unknown; no burn-in when every
estimated parameter has a refined prior). Transports (serial, CAN, Modbus,
real or emulated) only carry commands and replies; no rule lives in them.

Commands and what they require (NAK code when refused):

=================  ======================================================================================
STREAM_CONTROL     always accepted; the Ack's value of a start is the frame counter (low 32 bits) of the stream's first
                   exposure (:attr:`Firmware.next_frame` when the stream started; a start while streaming changes
                   nothing and carries the same value), of a stop 0
STAGE_BEGIN        length == TABLE_BYTES (92) (BAD_LENGTH); the session record persisted (BANK_WRITE_FAILED);
                   the Ack's value is the new staging session's nonce
STAGE_CHUNK        an upload in progress (NOT_STAGED); chunk inside the table (BAD_LENGTH); un-verifies
STAGE_VERIFY       staged set complete (NOT_STAGED), CRC matches (BAD_CRC), check_plausible against the
                   sensor's declared design and validate_sigma (INVALID_PARAMS, naming the rule)
READ_STAGED        staged set complete (NOT_STAGED)
COMMIT             the current session's nonce and the active generation (STALE_SESSION); verified, CRC
                   equal to the verified one (NOT_VERIFIED); sector read-back (BANK_WRITE_FAILED)
READ_ACTIVE        a committed set exists (NOT_STAGED)
READ_ESTIMATE      an estimator with at least one update (NO_ESTIMATE)
=================  ======================================================================================

Pure: no I/O, no clock, no threads (time comes in with each frame). The estimator is plugged in through a small
seam (:class:`EstimatorSeam`); :class:`RecursiveEstimator` adapts ``onboard.recursive`` to it. The C translation is
``onboard/c/firmware.c`` (the seam: ``estimator_seam.h``), held to the same replies byte for byte
(docs/port-kit.md, section 6).

Precision: the sensor's arithmetic is one option of its estimator, ``RecursiveEstimator(precision=...)``
(:data:`PRECISIONS`): ``"float32"``, a single-precision FPU, or ``"fixed"``, a sensor without one, whose per-star front
end (centroids in Q10 px, catalogue vectors and the camera model in Q30, exact Q61 interstar residuals:
``onboard.fixedpoint``) runs in integers and whose filter runs in float32 by a soft-float library.
:func:`estimator_update` is the one per-frame entry, shared with the host's ``hostlink replay``.

Scheduling: the estimator is the sensor's background task. Which exposures it processes is decided by a modelled
budget (:class:`EstimatorBudget`: the estimator's declared worst-case cost per update against the time between
exposures, both in the sensor's own time, which comes with each frame), never by how fast the machine running this
model happens to be; the same frames and budget give the same sequence of estimates everywhere. Exposures that
arrive while the modelled processor is still busy are counted in ``Counters.estimator_skipped``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from onboard import banks, fixedpoint, recursive
from onboard.params import ESTIMATE_NAMES, CameraParams
from onboard.prior import prior_config
from protocol.messages import (
    Ack,
    CentroidFrame,
    Commit,
    Estimate,
    EstimateStatus,
    GetStatus,
    Message,
    Nak,
    NakCode,
    ParamTable,
    ReadActive,
    ReadEstimate,
    ReadStaged,
    StageBegin,
    StageChunk,
    StageVerify,
    StreamControl,
    TableBank,
    Telemetry,
)


class EstimatorSeam(Protocol):
    """What the firmware needs from the onboard recursive estimator (``onboard.recursive``)."""

    def start(self, nominal: CameraParams, sigma: np.ndarray | None = None) -> Any:
        """A fresh estimator state starting from the active set ``nominal`` and its 1-sigma prior ``sigma`` (10 values,
        ESTIMATE_NAMES order, parameter units; NaN or 0 = unknown: the cold-start prior)."""

    def update(self, state: Any, x_px: np.ndarray, y_px: np.ndarray, r_ref: np.ndarray, identified: np.ndarray) -> None:
        """One frame: centroids [px] and reference unit vectors (N, 3) as the frame and the catalogue hold them
        (float64; the estimator takes them in its own precision), identified mask."""

    def estimate(self, state: Any) -> tuple[np.ndarray, np.ndarray, int, int]:
        """(values, sigma, estimated_mask, n_updates): values and 1-sigma in ESTIMATE_NAMES order, f in mm
        (float32, sigma NaN where unknown), bit i of the mask = ESTIMATE_NAMES[i] is estimated."""

    def cost_flops(self, n_stars: int) -> int:
        """Declared worst-case floating-point operations of one update with ``n_stars`` identified stars."""


@dataclass(frozen=True)
class EstimatorBudget:
    """The sensor's processor as its scheduler models it.

    An exposure taken at sensor time t is given to the estimator when the modelled processor is idle at t; it is then
    busy until t + cost / ``flops_per_s`` (cost: :meth:`EstimatorSeam.cost_flops`, the worst case). Exposures whose
    time does not advance (a session with one time for every frame) are taken ``min_frame_period_s`` apart, the
    sensor's fastest frame rate. The default, 50 Mflop/s sustained, is a Cortex-M7-class single-precision FPU: the
    worst case of 30 stars and 10 parameters (0.86 Mflop) takes 17 ms, so every exposure at up to 50 Hz is processed.
    """

    flops_per_s: float = 50e6
    min_frame_period_s: float = 0.1

    def busy_us(self, flops: int) -> int:
        """Modelled processor time of ``flops`` operations [us], rounded up."""
        return int(np.ceil(flops * 1e6 / self.flops_per_s))


@dataclass
class Counters:
    frames_processed: int = 0
    last_frame: int = 0
    estimator_faults: int = 0
    #: exposures given to the estimator / skipped because the modelled processor was still busy (EstimatorBudget)
    estimator_runs: int = 0
    estimator_skipped: int = 0


class Firmware:
    """One sensor's state: banks, stream flag, estimator state, counters."""

    def __init__(
        self, store: banks.BankStore, estimator: EstimatorSeam | None = None, budget: EstimatorBudget | None = None
    ) -> None:
        self.store = store
        self.streaming = False
        self.counters = Counters()
        #: frame counter (low 32 bits) the camera gives the next exposure: the last exposure's + 1, or what the
        #: camera's driver announced (:meth:`set_next_frame`); 0 after boot
        self.next_frame = 0
        self.stream_first_frame = 0  # the counter the current stream's start was acknowledged with
        self.budget = budget or EstimatorBudget()
        if not (np.isfinite(self.budget.flops_per_s) and self.budget.flops_per_s > 0):
            raise ValueError("the estimator budget needs flops_per_s > 0")
        if not (np.isfinite(self.budget.min_frame_period_s) and self.budget.min_frame_period_s > 0):
            raise ValueError("the estimator budget needs min_frame_period_s > 0")
        self._sensor_time_us: int | None = None  # time of the last exposure, as the scheduler saw it
        self._busy_until_us: int | None = None  # the modelled processor is busy with the estimator until then
        self._estimator = estimator
        self._est_state: Any = None
        self._est_generation = 0
        self._est_last_frame = 0
        self._restart_estimator()
        self._handlers: dict[type, Callable[[Any], Message]] = {
            GetStatus: self._status,
            StreamControl: self._stream_control,
            StageBegin: self._stage_begin,
            StageChunk: self._stage_chunk,
            StageVerify: self._stage_verify,
            ReadStaged: self._read_staged,
            Commit: self._commit,
            ReadActive: self._read_active,
            ReadEstimate: self._read_estimate,
        }

    # ------------------------------------------------------------------------------------------- commands
    def handle(self, command: Message) -> Message:
        """One command -> its reply (Ack, Nak, Telemetry, ParamTable or Estimate). Never raises for bad input."""
        handler = self._handlers.get(type(command))
        if handler is None:
            return Nak(
                tag=getattr(command, "tag", 0),
                command=int(getattr(command, "TYPE", 0)),
                code=NakCode.UNKNOWN_COMMAND,
                text=f"{type(command).__name__} is not a command",
            )
        return handler(command)

    def _ack(self, cmd: Message, value: int = 0) -> Ack:
        return Ack(tag=cmd.tag, command=int(cmd.TYPE), value=value)

    def _nak(self, cmd: Message, refusal: banks.Refusal) -> Nak:
        return Nak(tag=cmd.tag, command=int(cmd.TYPE), code=int(refusal.code), text=refusal.text)

    def _ack_or_nak(self, cmd: Message, refusal: banks.Refusal | None) -> Message:
        return self._ack(cmd) if refusal is None else self._nak(cmd, refusal)

    def _status(self, cmd: GetStatus) -> Telemetry:
        active = banks.active_set(self.store)
        return Telemetry(
            tag=cmd.tag,
            streaming=self.streaming,
            stage_state=int(self.store.stage_state),
            active_generation=0 if active is None else active[0],
            active_crc32=0 if active is None else active[2],
            frames_processed=self.counters.frames_processed,
            last_frame=self.counters.last_frame,
            estimator_updates=self._estimate_tuple()[3] if self._est_state is not None else 0,
        )

    def _stream_control(self, cmd: StreamControl) -> Ack:
        if not cmd.enable:
            self.streaming = False
            return self._ack(cmd)
        if not self.streaming:  # a new stream: its first exposure is the camera's next one
            self.streaming = True
            self.stream_first_frame = self.next_frame
        return self._ack(cmd, value=self.stream_first_frame)

    def set_next_frame(self, frame: int) -> None:
        """The camera's driver announces the frame counter of the next exposure (a camera whose counter does not
        simply follow the last exposure's, e.g. frames taken while not streaming, or a replayed session)."""
        self.next_frame = int(frame) & 0xFFFFFFFF

    def _stage_begin(self, cmd: StageBegin) -> Message:
        result = banks.stage_begin(self.store, cmd.length)
        if isinstance(result, banks.Refusal):
            return self._nak(cmd, result)
        return self._ack(cmd, value=result)  # the staging session's nonce: COMMIT must carry it

    def _stage_chunk(self, cmd: StageChunk) -> Message:
        return self._ack_or_nak(cmd, banks.stage_chunk(self.store, cmd.offset, cmd.data))

    def _stage_verify(self, cmd: StageVerify) -> Message:
        return self._ack_or_nak(cmd, banks.stage_verify(self.store, cmd.crc32))

    def _read_staged(self, cmd: ReadStaged) -> Message:
        staged = banks.staged_set(self.store)
        if staged is None:
            return self._nak(cmd, banks.Refusal(NakCode.NOT_STAGED, "no complete staged set"))
        table, crc = staged
        return ParamTable(tag=cmd.tag, bank=TableBank.STAGED, generation=0, crc32=crc, table=table)

    def _commit(self, cmd: Commit) -> Message:
        result = banks.commit(self.store, cmd.crc32, cmd.nonce, cmd.expected_generation)
        if isinstance(result, banks.Refusal):
            return self._nak(cmd, result)
        self._restart_estimator()
        return self._ack(cmd, value=result)

    def _read_active(self, cmd: ReadActive) -> Message:
        active = banks.active_set(self.store)
        if active is None:
            return self._nak(cmd, banks.Refusal(NakCode.NOT_STAGED, "no parameter set has been committed"))
        generation, table, crc = active
        return ParamTable(tag=cmd.tag, bank=TableBank.ACTIVE, generation=generation, crc32=crc, table=table)

    def _read_estimate(self, cmd: ReadEstimate) -> Message:
        if self._estimator is None:
            return self._nak(cmd, banks.Refusal(NakCode.NO_ESTIMATE, "this sensor has no onboard estimator"))
        if self._est_state is None:
            return self._nak(cmd, banks.Refusal(NakCode.NO_ESTIMATE, "no active parameter set to start from"))
        values, sigma, mask, n_updates = self._estimate_tuple()
        if n_updates == 0:
            return self._nak(cmd, banks.Refusal(NakCode.NO_ESTIMATE, "the estimator has not processed a frame yet"))
        return Estimate(
            tag=cmd.tag,
            status=EstimateStatus.RUNNING,
            estimated_mask=mask,
            base_generation=self._est_generation,
            n_updates=n_updates,
            last_frame=self._est_last_frame,
            values=tuple(float(v) for v in np.asarray(values, dtype=np.float32)),
            sigma=tuple(float(v) for v in np.asarray(sigma, dtype=np.float32)),
        )

    # --------------------------------------------------------------------------------------------- frames
    def process_frame(self, frame: CentroidFrame, r_ref: np.ndarray | None) -> bool:
        """One exposure: :meth:`count_frame`, then :meth:`estimate_frame` if the modelled budget leaves the processor
        idle at the exposure's time (:class:`EstimatorBudget`). Returns whether the estimator ran."""
        self.count_frame(frame)
        t_us = int(frame.t_us)
        if self._sensor_time_us is not None and t_us <= self._sensor_time_us:
            t_us = self._sensor_time_us + int(round(self.budget.min_frame_period_s * 1e6))
        self._sensor_time_us = t_us
        if self._estimator is None or self._est_state is None or r_ref is None or frame.n_stars == 0:
            return False
        if self._busy_until_us is not None and t_us < self._busy_until_us:
            self.counters.estimator_skipped += 1
            return False
        n_identified = int(np.count_nonzero(np.asarray(frame.star_id) != 0))
        self._busy_until_us = t_us + self.budget.busy_us(self._estimator.cost_flops(n_identified))
        self.counters.estimator_runs += 1
        self.estimate_frame(frame, r_ref)
        return True

    def count_frame(self, frame: CentroidFrame) -> None:
        """The exposure was taken (and is streamed): frame counters only, constant work."""
        self.counters.frames_processed += 1
        self.counters.last_frame = int(frame.frame)
        self.next_frame = (int(frame.frame) + 1) & 0xFFFFFFFF

    def estimate_frame(self, frame: CentroidFrame, r_ref: np.ndarray | None) -> None:
        """Run the estimator on an exposure's identified stars (``r_ref``: reference unit vectors (N, 3) from the
        catalogue, NaN rows for stars without one; None = no catalogue for this frame), unconditionally: which exposures
        reach it is :meth:`process_frame`'s decision."""
        if self._estimator is None or self._est_state is None or r_ref is None or frame.n_stars == 0:
            return
        r = np.asarray(r_ref, dtype=np.float64).reshape(-1, 3)
        identified = (np.asarray(frame.star_id) != 0) & np.all(np.isfinite(r), axis=1)
        try:
            with np.errstate(all="ignore"):
                self._estimator.update(
                    self._est_state,
                    np.asarray(frame.x_px, dtype=np.float64),
                    np.asarray(frame.y_px, dtype=np.float64),
                    np.where(identified[:, None], r, np.float64(0.0)),
                    identified,
                )
            self._est_last_frame = int(frame.frame)
        except (ArithmeticError, ValueError, np.linalg.LinAlgError):
            # a numerically failed update must not stop the sensor: count it and restart from the active set
            self.counters.estimator_faults += 1
            self._restart_estimator()

    # ----------------------------------------------------------------------------------------- estimator
    def _restart_estimator(self) -> None:
        active = banks.active_set(self.store)
        if self._estimator is None or active is None:
            self._est_state = None
            return
        self._est_generation = active[0]
        self._est_state = self._estimator.start(banks.table_to_params(active[1]), banks.table_to_sigma(active[1]))

    def _estimate_tuple(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        return self._estimator.estimate(self._est_state)


def estimate_to_params(active: CameraParams, estimate: Estimate) -> CameraParams:
    """The full parameter set an estimate stands for: the active set with the estimated values replaced."""
    values = np.asarray(estimate.values, dtype=np.float64)
    theta = active.vector(np.float64)
    mask = np.array([(estimate.estimated_mask >> i) & 1 for i in range(len(ESTIMATE_NAMES))], dtype=bool)
    theta[mask] = values[mask]
    return active.with_vector(theta)


def estimate_to_sigma(active_sigma: np.ndarray | None, estimate: Estimate) -> np.ndarray:
    """The 1-sigma prior an accepted estimate carries: the estimator's own sigma of each estimated parameter, the
    active set's (NaN = unknown when None) for the others, which the estimate left unchanged. ESTIMATE_NAMES order."""
    out = np.full(len(ESTIMATE_NAMES), np.nan) if active_sigma is None else np.array(active_sigma, dtype=np.float64)
    sigma = np.asarray(estimate.sigma, dtype=np.float64)
    mask = np.array([(estimate.estimated_mask >> i) & 1 for i in range(len(ESTIMATE_NAMES))], dtype=bool)
    out[mask] = sigma[mask]
    return out


#: ``accept`` commits an onboard estimate only after this many updates: the estimator's cold-start burn-in (its
#: distortion terms are held until then, ``onboard.recursive.RecursiveConfig.burn_in_frames``).
ACCEPT_MIN_UPDATES = recursive.RecursiveConfig().burn_in_frames
#: ... and when every estimated parameter's 1-sigma is at most this fraction of its cold-start prior sigma
#: (``onboard.recursive.default_prior_sigma``): the data then carry at least 15 times the prior's information
#: (1/0.25^2 - 1), so the estimate is the data's, not the prior's. Measured on the seed-004 simulation (0.05 px
#: noise): the largest ratio is 0.34 after 3 updates, 0.12 after 300 (principal point), 0.06 after 800.
ACCEPT_SIGMA_FRACTION = 0.25


def estimate_convergence(active: CameraParams, estimate: Estimate) -> str | None:
    """Why ``estimate`` (read from a sensor whose active set is ``active``) is not converged, or None if it is:
    at least ACCEPT_MIN_UPDATES updates, and each estimated parameter's sigma finite, > 0 and at most
    ACCEPT_SIGMA_FRACTION of its cold-start prior sigma."""
    if estimate.n_updates < ACCEPT_MIN_UPDATES:
        return f"only {estimate.n_updates} updates (at least {ACCEPT_MIN_UPDATES} needed)"
    prior = recursive.default_prior_sigma(active)
    sigma = np.asarray(estimate.sigma, dtype=np.float64)
    for i, name in enumerate(ESTIMATE_NAMES):
        if not (estimate.estimated_mask >> i) & 1:
            continue
        limit = ACCEPT_SIGMA_FRACTION * prior[i]
        if not (np.isfinite(sigma[i]) and 0 < sigma[i] <= limit):
            return f"sigma of {name} is {sigma[i]:.3g}, above {ACCEPT_SIGMA_FRACTION:g} of its prior ({limit:.3g})"
    return None


#: The sensor's precisions: "float32" (a single-precision FPU) and "fixed" (no FPU: the integer front end of
#: ``onboard.fixedpoint``, the filter in soft float32). The host's reference, float64, runs the same code.
PRECISIONS = ("float32", "fixed")


def precision_dtype(precision: str) -> np.dtype:
    """The estimator's float dtype in a precision: float32 for "float32" and "fixed" (its filter), float64 for the
    host's "float64" reference. Anything else is a ValueError naming the choices."""
    if precision not in (*PRECISIONS, "float64"):
        raise ValueError(f"unknown precision {precision!r} (expected one of {', '.join(PRECISIONS)} or float64)")
    return np.dtype(np.float64) if precision == "float64" else np.dtype(np.float32)


def estimator_update(
    state: recursive.RecursiveState,
    x_px: np.ndarray,
    y_px: np.ndarray,
    r_ref: np.ndarray,
    identified: np.ndarray | None,
    precision: str = "float32",
) -> recursive.FrameResult:
    """One frame of the onboard recursive estimator in ``precision``: the one per-frame entry of the sensor's
    firmware (:class:`RecursiveEstimator`) and of the host's replay. "fixed": :func:`onboard.fixedpoint.update`
    (centroids taken in Q10 px, references in Q30; raises ``FixedRangeError``, a ValueError, outside the proved
    range); otherwise :func:`onboard.recursive.update` in the state's dtype."""
    if precision == "fixed":
        return fixedpoint.update(state, x_px, y_px, r_ref, identified)
    return recursive.update(state, x_px, y_px, r_ref, identified)


@dataclass
class RecursiveEstimator:
    """``onboard.recursive`` behind the firmware's seam, in the sensor's ``precision`` (:data:`PRECISIONS`; float32 by
    default). ``dtype`` float64 gives the host's reference of the float32 sensor (same code)."""

    estimate_names: tuple[str, ...] = ESTIMATE_NAMES
    config: recursive.RecursiveConfig | None = None
    dtype: type = np.float32
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r} (expected one of {', '.join(PRECISIONS)})")
        if self.precision == "fixed" and np.dtype(self.dtype) != np.float32:
            raise ValueError("the fixed-point sensor's filter runs in float32")

    def start(self, nominal: CameraParams, sigma: np.ndarray | None = None) -> recursive.RecursiveState:
        config = prior_config(self.config, nominal, sigma, self.estimate_names)
        return recursive.create(nominal, self.estimate_names, config, self.dtype)

    def update(
        self,
        state: recursive.RecursiveState,
        x_px: np.ndarray,
        y_px: np.ndarray,
        r_ref: np.ndarray,
        identified: np.ndarray,
    ) -> None:
        estimator_update(state, x_px, y_px, r_ref, identified, self.precision)

    def cost_flops(self, n_stars: int) -> int:
        return recursive.update_cost_flops(n_stars, len(self.estimate_names), self.config)

    def estimate(self, state: recursive.RecursiveState) -> tuple[np.ndarray, np.ndarray, int, int]:
        values = recursive.current_params(state).vector(np.float32)
        sigma = np.full(len(ESTIMATE_NAMES), np.nan, dtype=np.float32)
        for name, value in recursive.sigma(state).items():
            sigma[ESTIMATE_NAMES.index(name)] = value
        mask = 0
        for k in state.idx:
            mask |= 1 << int(k)
        return values, sigma, mask, int(state.updates)
