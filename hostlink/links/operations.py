"""The host's operations on a sensor, written once over the :class:`~hostlink.links.base.Link` interface, so they
are the same on serial, CAN and Modbus, and against real or emulated sensors.

* :func:`stream_frames`: record N centroid frames, counting lost messages from sequence numbers;
* :func:`safe_upload`: the six-step safe upload (issue 6):
  1. the host reads the active set (its generation) and checks the new set's plausibility
     (``onboard.params.check_plausible``, the sensor's own rules, and ``onboard.prior.validate_sigma``);
  2. the host opens a staging session (the sensor answers with a fresh nonce, bound to that sensor and that
     moment: an opaque value to the host, never 0) and stages its float32 table
     (``protocol.param_table``: the camera parameters and their 1-sigma prior, which the sensor's estimator restarts
     from) on the sensor in chunks;
  3. the sensor verifies the staged bytes against the CRC-32 and its plausibility rules (NAK naming the rule);
  4. the host reads the staged set back and compares it byte for byte;
  5. the sensor commits it to its inactive A/B bank with the next generation and CRC, and switches atomically, only
     if the COMMIT carries the session's nonce and the generation read in step 1 (recorded, stale or reordered
     traffic commits nothing);
  6. the host reads the active set back: success only if it equals the uploaded table (float32, bit for bit) under
     the new generation.
  Until step 5 nothing on the sensor but its staging area and its session counter changes, so an interrupted upload
  leaves the old set active; the firmware (``onboard.firmware``) enforces that order whatever the host does.
* :func:`read_active_params`, :func:`read_estimate`, :func:`accept_estimate` (the onboard estimate committed through
  the same safe upload).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hostlink.errors import LinkError, UserError
from hostlink.files.session import Session
from hostlink.files.times import t_us_to_iso
from hostlink.links.base import CommandRefused, Link
from onboard.banks import params_to_table, table_to_params, table_to_sigma
from onboard.firmware import estimate_convergence, estimate_to_params, estimate_to_sigma
from onboard.params import CameraParams, ParameterError, PlausibilityLimits, check_plausible
from onboard.prior import sigma_to_dict, validate_sigma
from protocol.messages import ESTIMATE_FIELDS, CentroidFrame, Estimate, NakCode
from protocol.param_table import TABLE_BYTES, camera_file_from_fields, table_crc, table_to_mapping


class UploadMismatch(UserError):
    """A read-back (staged or active) differs from what was uploaded: the upload is not confirmed."""

    exit_code = 5


# ---------------------------------------------------------------------------------------------------- streaming
@dataclass(frozen=True)
class EstimatePoll:
    """One read of the onboard estimate during a stream: after ``frames_received`` frames, the ``estimate`` (None
    while the sensor has none yet, with its ``reason``)."""

    frames_received: int
    estimate: Estimate | None
    reason: str = ""
    #: False when the sensor's reply never came (a tolerated miss of :func:`stream_frames`, ``reason`` says why)
    answered: bool = True


@dataclass
class StreamResult:
    #: the frames received (empty when the stream was asked not to keep them)
    frames: list[CentroidFrame] = field(default_factory=list)
    frames_received: int = 0
    stars_received: int = 0
    lost_messages: int = 0
    corrupt_frames: int = 0
    #: True when the sensor reported the end of its source before N frames arrived.
    ended: bool = False
    polls: list[EstimatePoll] = field(default_factory=list)

    @property
    def n_stars(self) -> int:
        return self.stars_received

    @property
    def estimates(self) -> list[Estimate]:
        """The polls that returned an estimate, in order."""
        return [p.estimate for p in self.polls if p.estimate is not None]


def poll_estimate(link: Link, frames_received: int = 0) -> EstimatePoll:
    """Read the onboard estimate; a sensor that has none yet (NAK NO_ESTIMATE: no frame processed since its last
    restart, or no estimator) gives an :class:`EstimatePoll` without one instead of an error."""
    try:
        return EstimatePoll(frames_received, link.read_estimate())
    except CommandRefused as exc:
        if exc.code != NakCode.NO_ESTIMATE:
            raise
        return EstimatePoll(frames_received, None, exc.text)


def stream_frames(
    link: Link,
    n_frames: int | None,
    progress: Callable[[int], None] | None = None,
    frame_timeout_s: float | None = None,
    result: StreamResult | None = None,
    *,
    on_frame: Callable[[CentroidFrame], None] | None = None,
    keep_frames: bool = True,
    poll_every_frames: int = 0,
    poll_every_s: float = 0.0,
    max_polls: int | None = None,
    on_poll: Callable[[EstimatePoll], None] | None = None,
    keep_polls: bool = True,
    missed_polls_allowed: int = 0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> StreamResult:
    """The one stream loop (``stream``, ``monitor`` and the bench): start the stream, receive frames until
    ``n_frames`` arrived (None: no limit), the sensor's source ends, or ``max_polls`` polls were made; stop the stream.

    Each frame goes to ``on_frame`` and, if ``keep_frames``, into ``result.frames``. The onboard estimate is polled
    (:func:`poll_estimate`, tolerant of "no estimate yet") every ``poll_every_frames`` frames and/or every
    ``poll_every_s`` seconds; each poll goes to ``on_poll`` and, if ``keep_polls``, ``result.polls`` (a loop that runs
    until interrupted keeps neither frames nor polls, so its memory stays flat). After the source ended, time-based
    polls go on (the estimate is still readable) until ``max_polls``. Everything received is in ``result`` (pass your
    own to keep it when a LinkError or Ctrl-C interrupts the loop). Up to ``missed_polls_allowed`` polls in a row
    may go unanswered (a reply lost on a busy link): such a poll is reported with ``answered`` False and the stream
    goes on; one more raises the LinkError, and a link that is really gone ends the loop at the next frame anyway."""
    result = StreamResult() if result is None else result
    if poll_every_frames < 0 or poll_every_s < 0:
        raise ValueError("poll intervals must be >= 0")
    timed = poll_every_s > 0
    next_poll_t = clock() + poll_every_s
    poller = _Poller(link, result, on_poll, keep_polls, missed_polls_allowed, max_polls, n_polls=len(result.polls))
    link.set_streaming(True)
    try:
        while not poller.done() and (n_frames is None or result.frames_received < n_frames):
            if result.ended:
                if not timed:
                    break
                sleep(max(0.0, next_poll_t - clock()))
            else:
                frame = link.recv_frame(frame_timeout_s)
                if frame is None:
                    result.ended = True
                    continue
                _take_frame(result, frame, keep_frames, on_frame, progress)
                if poll_every_frames and result.frames_received % poll_every_frames == 0:
                    poller.poll()
                    continue
            if timed and clock() >= next_poll_t:
                poller.poll()
                next_poll_t = max(next_poll_t + poll_every_s, clock())
    finally:
        _stop_stream(link, result)
    return result


@dataclass
class _Poller:
    """The estimate polls of one stream loop: counted, kept and handed on; up to ``missed_allowed`` in a row may go
    unanswered (reported with ``answered`` False), one more raises the LinkError."""

    link: Link
    result: StreamResult
    on_poll: Callable[[EstimatePoll], None] | None
    keep: bool
    missed_allowed: int
    max_polls: int | None
    n_polls: int = 0
    missed_in_a_row: int = 0

    def poll(self) -> None:
        try:
            p = poll_estimate(self.link, self.result.frames_received)
            self.missed_in_a_row = 0
        except LinkError as exc:
            self.missed_in_a_row += 1
            if self.missed_in_a_row > self.missed_allowed:
                raise
            p = EstimatePoll(self.result.frames_received, None, str(exc), answered=False)
        self.n_polls += 1
        if self.keep:
            self.result.polls.append(p)
        if self.on_poll is not None:
            self.on_poll(p)

    def done(self) -> bool:
        return self.max_polls is not None and self.n_polls >= self.max_polls


def _take_frame(result: StreamResult, frame: CentroidFrame, keep_frames: bool, on_frame, progress) -> None:
    """Count a received frame into ``result``, keep it if asked, and hand it to ``on_frame`` and ``progress``."""
    result.frames_received += 1
    result.stars_received += frame.n_stars
    if keep_frames:
        result.frames.append(frame)
    if on_frame is not None:
        on_frame(frame)
    if progress is not None:
        progress(result.frames_received)


def _stop_stream(link: Link, result: StreamResult) -> None:
    """The link's loss counters into ``result``, then stop the stream, best effort: the frames are in hand, and a
    dropped link was already reported by recv_frame."""
    result.lost_messages = link.stats.lost_messages
    result.corrupt_frames = link.stats.corrupt_frames
    try:
        link.set_streaming(False)
    except (LinkError, UserError):
        pass


#: How received centroids are written to a session file: they arrive on the wire's 2**-10 px grid, and every value
#: n / 1024 has at most 10 decimals, so 10 decimals write them exactly.
WIRE_PX_FORMAT = "%.10f"


def frames_to_session(frames: list[CentroidFrame]) -> Session:
    """Received frames -> a session (columns frame, t_utc, star_id, x_px, y_px, mag; no reference directions)."""
    counts = [f.n_stars for f in frames]

    def cat(values: list[np.ndarray], dtype) -> np.ndarray:
        return np.concatenate(values).astype(dtype) if values else np.zeros(0, dtype)

    return Session(
        frame=np.repeat(np.array([f.frame for f in frames], dtype=np.int64), counts),
        t_utc=np.repeat(np.array([t_us_to_iso(f.t_us) for f in frames], dtype=object), counts),
        star_id=cat([f.star_id for f in frames], np.int64),
        x_px=cat([f.x_px for f in frames], np.float64),
        y_px=cat([f.y_px for f in frames], np.float64),
        mag=cat([f.mag for f in frames], np.float64),
    )


def record_session(
    link: Link,
    n_frames: int,
    path: str | Path,
    progress: Callable[[int], None] | None = None,
    result: StreamResult | None = None,
) -> StreamResult:
    """Record ``n_frames`` centroid frames (:func:`stream_frames`) into the session file ``path``, each frame written
    as it arrives (a partial file next to ``PATH``, renamed at the end: :class:`hostlink.files.session.SessionWriter`),
    centroids exactly as on the wire (:data:`WIRE_PX_FORMAT`).

    Interrupted after at least one frame (a :class:`UserError` such as a dropped link, or Ctrl-C), the frames
    received are committed to ``path`` and the exception goes on: a UserError as the same class and exit code with
    "the N frames received before were written to PATH" added, a KeyboardInterrupt as it is (``result``, passed in
    by the caller, says how many were kept). Interrupted before any frame, nothing is left behind."""
    from hostlink.files.session import SessionWriter

    if n_frames < 1:
        raise UserError("--frames must be >= 1")
    result = StreamResult() if result is None else result
    writer = SessionWriter(path, float_format=WIRE_PX_FORMAT)
    try:
        stream_frames(
            link,
            n_frames,
            progress=progress,
            result=result,
            keep_frames=False,
            on_frame=lambda frame: writer.append(frames_to_session([frame])),
        )
    except (UserError, KeyboardInterrupt) as exc:
        if not result.frames_received:
            writer.close_partial()
            if writer.partial is not None:
                writer.partial.unlink(missing_ok=True)
            raise
        writer.commit()
        if isinstance(exc, KeyboardInterrupt):
            raise
        err = type(exc)(f"{exc}; the {result.frames_received} frames received before were written to {path}")
        err.exit_code = exc.exit_code
        raise err from None
    writer.commit()
    return result


def poll_estimates(
    link: Link,
    count: int | None,
    interval_s: float,
    on_poll: Callable[[EstimatePoll], None],
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    """Read the onboard estimate (:func:`poll_estimate`) every ``interval_s`` seconds, ``count`` times (None: until
    interrupted), without starting the stream; each poll goes to ``on_poll``. Returns the number of polls made."""
    polls = 0
    while count is None or polls < count:
        sleep(interval_s)
        on_poll(poll_estimate(link))
        polls += 1
    return polls


def estimate_record(poll: EstimatePoll) -> dict:
    """One poll as a JSON-ready record: frames_received, and either estimate None with the sensor's reason, or the
    estimate's frame, updates, base_generation and each ESTIMATED parameter's value and 1-sigma (None = unknown)
    keyed by ``protocol.messages.ESTIMATE_FIELDS`` names (f in mm, x0/y0 in px)."""
    est = poll.estimate
    if est is None:
        record = {"frames_received": poll.frames_received, "estimate": None, "reason": poll.reason}
        return record if poll.answered else {**record, "answered": False}
    names = [n for i, n in enumerate(ESTIMATE_FIELDS) if est.estimated_mask >> i & 1]
    return {
        "frames_received": poll.frames_received,
        "frame": est.last_frame,
        "updates": est.n_updates,
        "base_generation": est.base_generation,
        "values": {n: est.values[ESTIMATE_FIELDS.index(n)] for n in names},
        "sigma": {n: _none_if_nan(est.sigma[ESTIMATE_FIELDS.index(n)]) for n in names},
    }


def _none_if_nan(value: float) -> float | None:
    return None if math.isnan(value) else value


# ------------------------------------------------------------------------------------------------------- upload
@dataclass(frozen=True)
class UploadResult:
    generation: int
    crc32: int
    active: CameraParams
    #: the active set's 1-sigma prior as read back (10 float32 values, ESTIMATE_NAMES order, NaN/0 = unknown)
    sigma: np.ndarray = field(default_factory=lambda: np.full(10, np.nan, dtype=np.float32))


def chunks(table: bytes, size: int) -> list[tuple[int, bytes]]:
    """(offset, bytes) pieces of at most ``size`` bytes covering ``table``."""
    if size < 1:
        raise ValueError("chunk size must be >= 1")
    return [(off, table[off : off + size]) for off in range(0, len(table), size)]


def safe_upload(
    link: Link,
    params: CameraParams,
    host_check: bool = True,
    step: Callable[[int, str], None] | None = None,
    sigma: np.ndarray | None = None,
) -> UploadResult:
    """The six-step safe upload (module docstring) of ``params`` with its 1-sigma prior ``sigma`` (10 values,
    ESTIMATE_NAMES order, parameter units; NaN or 0 = unknown; None = nothing known: the sensor's estimator restarts
    cold). Raises UserError (host refused), CommandRefused (sensor refused, with its reason), UploadMismatch (a
    read-back differs) or LinkError. ``step(k, text)`` reports progress."""

    def report(k: int, text: str) -> None:
        if step is not None:
            step(k, text)

    def host_refusal(limits: PlausibilityLimits | None) -> None:
        try:
            check_plausible(params, limits)
            if sigma is not None:
                validate_sigma(sigma)
        except ParameterError as exc:
            raise UserError(f"parameter set refused by the host check: {exc}") from None

    if host_check:
        host_refusal(None)  # everything but the focal-length rule, before a byte is sent
    try:  # the generation this upload replaces (COMMIT carries it)
        current = read_active_params(link)
    except CommandRefused as exc:
        if exc.code != NakCode.NOT_STAGED:
            raise
        current = None  # blank flash: nothing committed yet, generation 0
    if host_check and current is not None:
        # the sensor's design focal length is known to the sensor only: the host holds the set to the same
        # tolerance around the active set's (which the sensor held to its design)
        host_refusal(PlausibilityLimits(current.params.focal_length_mm, design_name="active set's"))
    report(1, "validated on the host (plausibility)")
    table = params_to_table(params, sigma)
    crc = table_crc(table)
    nonce = link.stage_begin(len(table))
    for offset, piece in chunks(table, link.max_chunk_bytes):
        link.stage_chunk(offset, piece)
    report(2, f"staged {len(table)} bytes in {-(-len(table) // link.max_chunk_bytes)} chunks")
    link.stage_verify(crc)
    report(3, f"sensor verified CRC 0x{crc:08x} and ranges")
    staged = link.read_staged()
    if bytes(staged.table) != table or staged.crc32 != crc:
        raise UploadMismatch(
            f"staged set read back differs from the upload (CRC 0x{staged.crc32:08x}, expected "
            f"0x{crc:08x}); nothing was committed"
        )
    report(4, "staged set read back equal")
    generation = link.commit(crc, nonce=nonce, expected_generation=0 if current is None else current.generation)
    report(5, f"committed as generation {generation}")
    active = link.read_active()
    if bytes(active.table) != table or active.crc32 != crc or active.generation != generation:
        raise UploadMismatch(
            f"active set read back (generation {active.generation}, CRC 0x{active.crc32:08x}) is "
            f"not the upload (generation {generation}, CRC 0x{crc:08x})"
        )
    report(6, "active set read back equal")
    return UploadResult(
        generation=generation,
        crc32=crc,
        active=table_to_params(bytes(active.table)),
        sigma=table_to_sigma(bytes(active.table)),
    )


def float32_equal(
    a: CameraParams, b: CameraParams, sigma_a: np.ndarray | None = None, sigma_b: np.ndarray | None = None
) -> bool:
    """Every parameter of ``a`` and ``b`` (and their sigmas, None = unknown) equal after rounding to float32, bit for
    bit (docs/commands.md, ``hostlink upload``)."""
    return params_to_table(a, sigma_a) == params_to_table(b, sigma_b)


# --------------------------------------------------------------------------------------------- params / estimate
@dataclass(frozen=True)
class ActiveParams:
    params: CameraParams
    generation: int
    crc32: int
    #: the set's 1-sigma prior (10 float32 values, ESTIMATE_NAMES order, NaN/0 = unknown)
    sigma: np.ndarray = field(default_factory=lambda: np.full(10, np.nan, dtype=np.float32))


def read_active_params(link: Link) -> ActiveParams:
    """The sensor's active set, its generation and CRC (the CRC is checked against the table received), with its
    1-sigma prior (10 float32 values, NaN = unknown). Raises LinkError when the bytes do not match their CRC or are
    not a parameter set, or the link fails."""
    active = link.read_active()
    table = bytes(active.table)
    if len(table) != TABLE_BYTES or table_crc(table) != active.crc32:
        raise LinkError(f"{link.name}: active set arrived with a CRC that does not match its bytes")
    try:
        params = table_to_params(table)
    except ParameterError as exc:
        raise LinkError(f"{link.name}: active set is not a parameter set ({exc})") from None
    return ActiveParams(params=params, generation=active.generation, crc32=active.crc32, sigma=table_to_sigma(table))


def read_estimate(link: Link) -> Estimate:
    """The sensor's onboard recursive estimate (values in parameter units: f [mm], x0/y0 [px], distortion; its
    1-sigma; updates; last frame). Raises CommandRefused (NAK NO_ESTIMATE) while it has none: use
    :func:`poll_estimate` to treat that as "not yet"; LinkError when the link fails."""
    return link.read_estimate()


def accept_estimate(
    link: Link, step: Callable[[int, str], None] | None = None, force: bool = False
) -> tuple[UploadResult, Estimate]:
    """Commit the sensor's current onboard estimate, with its own 1-sigma as the new set's prior (the active set's
    sigma for parameters it does not estimate), through the safe upload. Refused (UserError) if the estimate started
    from another set than the active one (it was read across a commit), is not converged
    (:func:`onboard.firmware.estimate_convergence`; ``force`` skips that test only) or fails the plausibility
    check."""
    active = read_active_params(link)
    estimate = link.read_estimate()
    if estimate.base_generation != active.generation:
        raise UserError(
            f"the onboard estimate started from generation {estimate.base_generation} but generation "
            f"{active.generation} is active; read it again"
        )
    why = None if force else estimate_convergence(active.params, estimate)
    if why is not None:
        raise UserError(f"the onboard estimate has not converged: {why} (--force commits it anyway)")
    params = estimate_to_params(active.params, estimate)
    sigma = estimate_to_sigma(active.sigma, estimate)
    return safe_upload(link, params, step=step, sigma=sigma), estimate


def shortest_float32(value: float) -> float:
    """The shortest decimal that reads back as the same float32 (what ``hostlink params`` prints)."""
    return float(str(np.float32(value)))


def params_float32_dict(params: CameraParams, sigma: np.ndarray | None = None) -> dict:
    """A camera parameter file object with every value written as its shortest float32 decimal, plus a ``sigma``
    object (the set's 1-sigma prior, null = unknown) when any sigma is known."""
    table = params_to_table(params, sigma)
    out = camera_file_from_fields({name: shortest_float32(v) for name, v in table_to_mapping(table).items()})
    sig = sigma_to_dict(table_to_sigma(table), shortest_float32)
    if sig is not None:
        out["sigma"] = sig
    return out
