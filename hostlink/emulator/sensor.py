"""The emulated sensor that every endpoint (serial, CAN, Modbus) hosts: firmware + frame source, thread-safe.

Frame sources hold what a real sensor holds: the centroids it measures and, for each identified star, the reference
direction its onboard catalogue gives (here from the session's ``ra_deg``/``dec_deg`` columns, simulated or replayed;
stars without one are passed to the estimator as unidentified). The emulated camera takes an exposure only when
the host drains one, i.e. while streaming (the firmware then decides, by its modelled budget, whether the estimator
processes it), so ``--replay`` streams the file's rows from its first frame, exactly once,
then reports :class:`~protocol.messages.EndOfStream`. The simulated source cycles through its frames forever,
continuing the frame counter and the clock.

:class:`Pacer` keeps an endpoint at its physical line rate (serial: 10 bits per byte at the baud rate; CAN: bits per
frame at the bit rate).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from hostlink.files.session import Session
from hostlink.files.times import iso_to_t_us
from onboard.camera import radec_to_unit
from onboard.firmware import Firmware
from protocol.messages import MAG_FIXED, MAX_STARS, Ack, CentroidFrame, EndOfStream, Message, StreamControl


@dataclass(frozen=True)
class SourceFrame:
    """One exposure as the emulated sensor sees it: the frame and the catalogue's reference unit vectors (N, 3)
    (NaN rows for unidentified stars; None when the source has no reference directions)."""

    frame: CentroidFrame
    r_ref: np.ndarray | None


@dataclass
class EndpointOptions:
    """Settings an endpoint reads (``hostlink emulate`` options)."""

    baud: int = 921_600
    bitrate: int = 1_000_000
    host: str = "127.0.0.1"
    port: int = 0
    unit: int = 1
    #: Test hook: drop every Kth stream message after it was numbered (0 = never), so loss counting is testable.
    drop_every: int = 0
    extra: dict[str, object] = field(default_factory=dict)  # --option settings, parsed (emulator.setup)


#: Largest magnitude the wire carries: int16 millimagnitudes (``protocol.messages.MAG_FIXED``; -32768 = none).
_WIRE_MAG_LIMIT = 32767 / MAG_FIXED.steps_per_unit
#: Star ids and frame counters travel as uint32 (``protocol.messages.CentroidFrame``).
_WIRE_U32_END = 1 << 32


def _check_wire_ranges(session: Session) -> None:
    """ValueError (naming the file line) for a star the sensor could not send: a magnitude beyond the wire's range
    (NaN is "none"), or a star id or frame counter outside uint32. Centroids are checked against the detector by
    the caller."""
    checks = []
    if session.mag is not None:
        mag = np.asarray(session.mag, dtype=np.float64)
        beyond = np.abs(np.nan_to_num(mag, nan=0.0)) > _WIRE_MAG_LIMIT  # (an infinity too; NaN is "none")
        checks.append(("mag", mag, beyond, f"within +-{_WIRE_MAG_LIMIT}"))
    for name in ("star_id", "frame"):
        ids = np.asarray(getattr(session, name), dtype=np.int64)
        checks.append((name, ids, (ids < 0) | (ids >= _WIRE_U32_END), f"in 0..{_WIRE_U32_END - 1}"))
    for name, values, bad, allowed in checks:
        if np.any(bad):
            k = int(np.argmax(bad))
            raise ValueError(f"line {k + 2}: {name} {values[k].item()!r} is not one the sensor sends ({allowed})")


def session_frames(session: Session, cycle: bool = False) -> Iterator[SourceFrame]:
    """Frames of a session in file order (``cycle``: forever, shifting the frame counter and the clock by the
    session's span each pass). At most MAX_STARS stars per frame (a session with more is refused up front)."""
    slices = list(session.frame_slices())
    if not slices:
        return
    counts = [s.stop - s.start for s in slices]
    if max(counts) > MAX_STARS:
        raise ValueError(f"a frame has {max(counts)} stars; the sensor's frame buffer holds {MAX_STARS}")
    _check_wire_ranges(session)
    t_us = np.array([iso_to_t_us(session.t_utc[s.start]) for s in slices], dtype=np.int64)
    frames = np.array([int(session.frame[s.start]) for s in slices], dtype=np.int64)
    have_ref = session.ra_deg is not None and session.dec_deg is not None
    if have_ref:
        r_all = radec_to_unit(np.radians(session.ra_deg), np.radians(session.dec_deg))
    mag = session.mag if session.mag is not None else np.full(len(session), np.nan)
    frame_step = int(frames[-1] - frames[0]) + 1
    t_step = int(t_us[-1] - t_us[0]) + (int(t_us[1] - t_us[0]) if len(t_us) > 1 else 1_000_000)
    n_pass = 0
    while True:
        for k, s in enumerate(slices):
            yield SourceFrame(
                frame=CentroidFrame(
                    frame=int(frames[k] + n_pass * frame_step),
                    t_us=int(t_us[k] + n_pass * t_step),
                    star_id=session.star_id[s].astype(np.uint32),
                    x_px=session.x_px[s],
                    y_px=session.y_px[s],
                    mag=mag[s],
                ),
                r_ref=r_all[s] if have_ref else None,
            )
        if not cycle:
            return
        n_pass += 1


class EmulatedSensor:
    """Firmware + frame source behind a lock: endpoints call :meth:`handle` and :meth:`next_stream_message` from any
    thread.

    Each exposure goes through :meth:`onboard.firmware.Firmware.process_frame` before it is streamed: the firmware's
    modelled budget (:class:`~onboard.firmware.EstimatorBudget`) decides whether the recursive estimator runs on it,
    so which frames are estimated depends only on the session and the options, never on how busy the host is. When
    the host machine is slower than the modelled sensor, the stream is slower than the line allows; the estimates
    are the same.
    """

    def __init__(self, firmware: Firmware, source: Iterator[SourceFrame], phase_starts: tuple[int, ...] = ()) -> None:
        self.firmware = firmware
        self._source = source
        #: frame counters where the source's phases begin (a bench's scene generator): a stream started after the
        #: camera took an exposure begins at the next phase start past that exposure, so the exposures a stopping
        #: stream took (in flight when the host stopped it) never shift the next phase
        self.phase_starts = tuple(sorted(int(s) for s in phase_starts))
        self._last_counter: int | None = None  # frame counter of the last exposure taken
        self._lock = threading.Lock()
        self._ended = False
        self._end_sent = False
        self.frames_sent = 0
        #: streams started so far (STREAM_CONTROL enable while not streaming): an endpoint restarts its stream
        #: message numbering when this changes
        self.streams_started = 0
        self._next: SourceFrame | None = None  # the next exposure, taken from the source to learn its counter

    @property
    def streaming(self) -> bool:
        return self.firmware.streaming

    def handle(self, command: Message) -> Message:
        """Decide one command (the firmware does) and return its reply. The ACK of STREAM_CONTROL(enable) carries
        the frame counter of the stream's first exposure (low 32 bits; the same for a repeated enable while the
        stream runs), so that the host counts the frames lost before the first one it receives."""
        with self._lock:
            starting = isinstance(command, StreamControl) and command.enable and not self.firmware.streaming
            if starting:
                self._skip_to_phase_start()
            if starting and self._peek_frame_counter() is not None:
                # the camera tells the firmware its next exposure's counter; the firmware's ACK carries it
                self.firmware.set_next_frame(self._peek_frame_counter())
            reply = self.firmware.handle(command)
            if starting and isinstance(reply, Ack):
                self._end_sent = False  # a restarted stream reports the end again if the source is exhausted
                self.streams_started += 1
            return reply

    def _skip_to_phase_start(self) -> None:
        """Move the source on to the first phase start past the last exposure taken (nothing before the first
        exposure, or past the last phase start): the frames skipped are never exposed."""
        if self._last_counter is None:
            return
        later = [s for s in self.phase_starts if s > self._last_counter]
        if not later:
            return
        while (counter := self._peek_frame_counter()) is not None and counter < later[0]:
            self._next = None

    def _peek_frame_counter(self) -> int | None:
        """The next exposure's frame counter (taken from the source and kept), None when the source is exhausted."""
        if self._next is None and not self._ended:
            try:
                self._next = next(self._source)
            except StopIteration:
                self._ended = True
        return self._next.frame.frame if self._next is not None else None

    def next_stream_message(self) -> CentroidFrame | EndOfStream | None:
        """While streaming: the next exposure (already seen by the firmware and, if its budget allowed, by the
        estimator), or EndOfStream once when the source is exhausted; None when not streaming (or after the end was
        reported)."""
        with self._lock:
            if not self.firmware.streaming:
                return None
            if self._ended:
                if self._end_sent:
                    return None
                self._end_sent = True
                return EndOfStream(frames_sent=self.frames_sent)
            try:
                item, self._next = (self._next, None) if self._next is not None else (next(self._source), None)
            except StopIteration:
                self._ended = True
                self._end_sent = True
                return EndOfStream(frames_sent=self.frames_sent)
            self.firmware.process_frame(item.frame, item.r_ref)
            self._last_counter = int(item.frame.frame)
            self.frames_sent += 1
            return item.frame


class Pacer:
    """Holds a sender to ``bits_per_s``: :meth:`wait` blocks until the line is free for the next ``n_bits``.

    The schedule is cumulative (the line is busy until ``free_at``), so sleep jitter does not accumulate; a sender
    that falls behind may catch up by at most ``credit_s`` (a UART FIFO's worth), never faster than the line on
    average.
    """

    def __init__(
        self,
        bits_per_s: float,
        credit_s: float = 0.005,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if bits_per_s <= 0:
            raise ValueError("line rate must be > 0")
        self.bits_per_s = float(bits_per_s)
        self.credit_s = float(credit_s)
        self._clock, self._sleep = clock, sleep
        self._free_at = clock()

    @property
    def free_at(self) -> float:
        """Clock time at which the line finishes the last message handed to :meth:`wait`."""
        return self._free_at

    def wait(self, n_bits: int) -> None:
        now = self._clock()
        start = max(self._free_at, now - self.credit_s)
        if start > now:
            self._sleep(start - now)
        self._free_at = start + n_bits / self.bits_per_s
