"""Cross-process power cuts against ``hostlink emulate --flash`` (issue 15: "kill -9 of the emulator at 200 random
points of uploads, restarted on the same --flash: the active set reads back as the complete old or complete new set
every time, never another").

Each trial runs the emulator (serial link, no estimator) on ONE flash file that every trial shares, uploads the other
of two parameter sets (they alternate) and kills the emulator with SIGKILL at a point drawn from the seeded RNG:

* even trials, from inside: ``--power-cut-after N``, the process kills itself after N 8-byte flash write units, N
  uniform over the units an upload writes (a session record, then a sector erase and a bank record: 528 units), so
  the cut lands on an exact byte of an erase or a program, whatever the speed of the machine;
* odd trials, from outside: ``kill -9`` after a delay uniform in [0, 1.5 T] from the start of the upload, T the
  duration of one whole upload measured at the start of the run (on the serial link about 25 ms): anywhere in the
  exchange (opening the link, staging, verify, commit, read-back) or just after it.

The emulator is then restarted on the same file and the active set is read back. Pass: its (generation, table) is
the complete old set or the complete new one (generation + 1). Anything else is a failure (exit 1).

Replays (issue 15: "replaying every recorded upload, in whole or in part, activates nothing"; serial transport): the
bytes the host wrote to the line in every upload are recorded (whole uploads, and the ones a cut ended). After each
restart, one recording drawn from all of them so far is sent again on the line, as another host would send it: whole,
a random byte prefix, or a random subset of its frames in random order; then the active set is read again. Pass: it
is unchanged (nothing activated). The first recording is a complete upload whose COMMIT went through.

Replays to other units, on every transport (``--unit-replays N``): N times, a new unit (a fresh --flash file) takes an
upload whose link calls (STAGE_BEGIN, the chunks, STAGE_VERIFY, COMMIT with its nonce) are recorded as the host made
them; then those calls are made again, as another host would, to another new unit and to the first unit restarted on
its flash. Pass: neither activates anything (the factory set, resp. the uploaded set, stays). The line recording
above is serial only; this one goes through each transport's own command path (CAN ISO-TP, Modbus registers).

Run (the acceptance run, 200 points and 200 replays; about 3 minutes on 2 cores)::

    .venv/bin/python scripts/flash_power_cuts.py --trials 200 --seed 1

``tests/test_emulator_flash.py`` runs the same trials, fewer of them, in CI.
"""

from __future__ import annotations

import argparse
import dataclasses
import random
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from hostlink.emulator.process import EmulatorProcess
from hostlink.errors import LinkError, UserError
from hostlink.links import open_link
from hostlink.links.base import CommandRefused
from hostlink.links.operations import safe_upload
from onboard import banks
from onboard.banks import BANK_RECORD_BYTES, SECTOR_BYTES, STAGE_RECORD_BYTES, WRITE_BYTES, params_to_table
from onboard.params import CameraParams, Distortion

#: Flash write units of one upload: the session record, the erase of the inactive sector, the bank record.
UPLOAD_UNITS = (STAGE_RECORD_BYTES + SECTOR_BYTES + BANK_RECORD_BYTES) // WRITE_BYTES
#: Outside kills land within this multiple of one upload's measured duration from the upload's start.
DELAY_FACTOR = 1.5
#: Emulator options: the link and the banks matter here, not the frames.
EMULATOR_ARGS = ("--no-estimator", "--sim-frames", "5")
#: The two sets the trials alternate between: the design camera and a calibrated one (both plausible).
SET_A = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))
SET_B = CameraParams(70.2262, 12.0, (500.0, 530.0), (1024, 1024), Distortion(k1=-2e-10, k2=3.5e-15))


@dataclasses.dataclass(frozen=True)
class Trial:
    index: int
    how: str  # "inside N" or "outside T s"
    outcome: str  # "old", "new" or a description of what else was found
    replay: str = ""  # what was replayed after the restart ("" when none)
    replay_outcome: str = ""  # "nothing activated" or what changed
    replay_sessions: int = 0  # staging sessions the replay opened on the sensor (its persisted session counter)


def read_active(link_string: str) -> tuple[int, bytes]:
    with open_link(link_string) as link:
        active = link.read_active()
    return active.generation, bytes(active.table)


def _upload(link_string: str, params: CameraParams, recording: bytearray | None = None) -> None:
    """A safe upload; with ``recording``, every byte the host writes to the serial line is appended to it."""
    try:
        with open_link(link_string, timeout_s=5.0) as link:
            if recording is not None:
                write = link._port.write  # the line itself: what a recorder on the wire would capture
                link._port.write = lambda data: (recording.extend(data), write(data))[1]
            safe_upload(link, params)
    except (LinkError, CommandRefused, UserError, OSError):
        pass  # the sensor died under the host: expected


def replay_piece(rng: random.Random, recording: bytes) -> tuple[str, bytes]:
    """What to send again of a recorded upload: the whole of it, a random byte prefix, or a random subset of its
    frames (each with its 0x00 delimiter) in random order; with a description."""
    frames = [f + b"\x00" for f in recording.split(b"\x00") if f]
    kind = rng.randrange(3)
    if kind == 0 or len(frames) < 2:
        return f"whole ({len(recording)} bytes)", recording
    if kind == 1:
        n = rng.randrange(1, len(recording))
        return f"prefix of {n} bytes", recording[:n]
    subset = rng.sample(frames, rng.randrange(1, len(frames) + 1))
    return f"{len(subset)} of {len(frames)} frames, shuffled", b"".join(subset)


def replay_on_line(link_string: str, data: bytes) -> tuple[int, bytes]:
    """Send recorded bytes on the sensor's line as they are, then read the active set on the same line (the sensor
    answers in order, so the replay has been handled when READ_ACTIVE's reply arrives)."""
    with open_link(link_string) as link:
        link._port.write(data)
        link._port.flush()
        active = link.read_active()
    return active.generation, bytes(active.table)


#: The link calls of an upload that a replay of it makes again.
UPLOAD_CALLS = ("stage_begin", "stage_chunk", "stage_verify", "commit")


def record_calls(link) -> list[tuple[str, tuple, dict]]:
    """Tap ``link``'s upload calls: each (name, args, kwargs) is appended to the returned list as it is made."""
    calls: list[tuple[str, tuple, dict]] = []
    for name in UPLOAD_CALLS:
        method = getattr(link, name)

        def tap(*args, _name=name, _method=method, **kwargs):
            calls.append((_name, args, kwargs))
            return _method(*args, **kwargs)

        setattr(link, name, tap)
    return calls


def replay_calls(link_string: str, calls: list[tuple[str, tuple, dict]]) -> tuple[tuple[int, bytes], int]:
    """Make recorded upload calls again on a sensor (refusals expected); returns its active set afterwards and how
    many calls it accepted."""
    accepted = 0
    with open_link(link_string, timeout_s=5.0) as link:
        for name, args, kwargs in calls:
            try:
                getattr(link, name)(*args, **kwargs)
                accepted += 1
            except CommandRefused:
                pass
        active = link.read_active()
    return (active.generation, bytes(active.table)), accepted


def unit_replays(
    n: int, workdir: Path, transport: str = "serial", firmware: str = "python"
) -> tuple[list[str], list[tuple[int, int]]]:
    """``n`` rounds of the module docstring's replays to other units on ``transport``. Returns a description of every
    replay that activated something (empty: none did) and, per replay, (calls accepted, calls made): a replay that
    reached the sensor has every call but the COMMIT accepted."""
    args = (*EMULATOR_ARGS, "--firmware", firmware)
    failures: list[str] = []
    reached: list[tuple[int, int]] = []
    for k in range(n):
        target = SET_B if k % 2 == 0 else SET_A
        recorder = workdir / f"unit-{k}-a.img"
        with EmulatorProcess(transport, args, flash_path=recorder) as emulator:
            with open_link(emulator.link, timeout_s=5.0) as link:
                calls = record_calls(link)
                safe_upload(link, target)
        for who, flash in (("a new unit", workdir / f"unit-{k}-b.img"), ("the same unit restarted", recorder)):
            with EmulatorProcess(transport, args, flash_path=flash) as emulator:
                before = read_active(emulator.link)
                after, accepted = replay_calls(emulator.link, calls)
            reached.append((accepted, len(calls)))
            if after != before:
                failures.append(f"round {k}, {who}: generation {before[0]} -> {after[0]} ({accepted} calls accepted)")
    return failures, reached


def session_counter(flash: Path) -> int:
    """The sensor's persisted staging-session counter, read from its flash image file as a boot would."""
    return banks.boot(banks.RamFlash(np.fromfile(flash, dtype=np.uint8))).nonce_counter


def run_trials(
    n_trials: int, seed: int, workdir: Path, transport: str = "serial", replays: bool = True, firmware: str = "python"
) -> list[Trial]:
    """``n_trials`` power cuts on one flash file in ``workdir``; returns each trial's outcome. Reading the active set
    writes nothing to flash, so the emulator restarted to check a trial is already armed for the next one. With
    ``replays`` (serial only), a recorded upload is sent again after each restart (module docstring). ``firmware``:
    the emulator's (``hostlink emulate --firmware``: python or c)."""
    emulator_args = (*EMULATOR_ARGS, "--firmware", firmware)
    rng = random.Random(seed)
    replay_rng = random.Random(seed + 1)  # its own stream: the cut points do not depend on whether replays run
    replays = replays and transport == "serial"
    recordings: list[bytes] = []
    flash = workdir / "flash.img"
    cut_units = [rng.randrange(UPLOAD_UNITS) if k % 2 == 0 else None for k in range(n_trials)]  # None: outside

    def start(k: int) -> EmulatorProcess:
        hook = () if k >= n_trials or cut_units[k] is None else ("--power-cut-after", str(cut_units[k]))
        return EmulatorProcess(transport, (*emulator_args, *hook), flash_path=flash)

    trials = []
    emulator = EmulatorProcess(transport, emulator_args, flash_path=flash)
    try:
        t0 = time.monotonic()
        first = bytearray()
        _upload(emulator.link, SET_B, first if replays else None)  # uncut: its duration scales the outside kills
        delay_max_s = DELAY_FACTOR * (time.monotonic() - t0)
        recordings.append(bytes(first))
        emulator.stop()
        emulator = start(0)
        before = read_active(emulator.link)
        for k in range(n_trials):
            target = SET_B if before[1] == params_to_table(SET_A) else SET_A
            recording = bytearray()
            upload = threading.Thread(target=_upload, args=(emulator.link, target, recording if replays else None))
            upload.start()
            how = _cut_power(emulator, upload, cut_units[k], rng, delay_max_s)
            emulator.stop()
            emulator = start(k + 1)
            after = read_active(emulator.link)
            outcome = _outcome(before, after, target)
            what, replay_outcome, opened = "", "", 0
            if replays:
                if recording:
                    recordings.append(bytes(recording))
                what, replay_outcome, opened, after = _replay_one(emulator.link, flash, recordings, replay_rng, after)
            trials.append(Trial(k, how, outcome, what, replay_outcome, opened))
            before = after
    finally:
        emulator.stop()
    return trials


def _cut_power(
    emulator: EmulatorProcess, upload: threading.Thread, cut_unit: int | None, rng: random.Random, delay_max_s: float
) -> str:
    """Power cut during the running ``upload``: by the emulator's armed hook after ``cut_unit`` units (inside), or
    without one (``cut_unit`` None: outside) by kill -9 at a random time up to ``delay_max_s`` [s]; the emulator
    killed in any case once the upload ends. Returns how it was cut."""
    if cut_unit is not None:  # inside: the armed hook cuts the power
        how = f"inside {cut_unit} units"
    else:  # outside: kill -9 at a random time of the upload
        delay_s = rng.uniform(0.0, delay_max_s)
        how = f"outside {delay_s:.3f} s"
        upload.join(delay_s)
        emulator.process.send_signal(signal.SIGKILL)
    upload.join(60.0)
    emulator.process.send_signal(signal.SIGKILL)  # if the hook's cut lay beyond this upload's writes
    return how


def _outcome(before: tuple[int, bytes], after: tuple[int, bytes], target) -> str:
    """What a restart after the cut booted: the old set (``before``), the new one (``target``, one generation on),
    or anything else (MIXED: a failure)."""
    if after == before:
        return "old"
    if after == (before[0] + 1, params_to_table(target)):
        return "new"
    return f"MIXED: generation {after[0]} (was {before[0]})"


def _replay_one(
    link: str, flash: Path, recordings: list[bytes], replay_rng: random.Random, after: tuple[int, bytes]
) -> tuple[str, str, int, tuple[int, bytes]]:
    """A piece of a recorded upload (:func:`replay_piece`) sent again on the line: what was sent, whether it
    activated anything, how many staging sessions it opened (> 0: it reached the sensor and was acted on), and the
    active set after it."""
    what, data = replay_piece(replay_rng, recordings[replay_rng.randrange(len(recordings))])
    counter = session_counter(flash)
    again = replay_on_line(link, data)
    opened = session_counter(flash) - counter
    replay_outcome = "nothing activated" if again == after else f"ACTIVATED: generation {again[0]}"
    return what, replay_outcome, opened, again


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--transport", default="serial", choices=("serial", "can", "modbus"))
    parser.add_argument("--no-replays", action="store_true", help="power cuts only (replays need --transport serial)")
    parser.add_argument("--firmware", default="python", choices=("python", "c"), help="the emulated sensor's firmware")
    parser.add_argument("--unit-replays", type=int, default=0, metavar="N", help="N uploads replayed to other units")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        trials = run_trials(args.trials, args.seed, Path(tmp), args.transport, not args.no_replays, args.firmware)
        unit_failures, reached = unit_replays(args.unit_replays, Path(tmp), args.transport, args.firmware)
    for failure in unit_failures:
        print(f"replay to {failure}: ACTIVATED")
    if args.unit_replays:
        all_but_commit = sum(accepted == made - 1 for accepted, made in reached)
        print(
            f"{args.unit_replays} recorded uploads ({args.transport}) replayed to a new unit and to the recording unit "
            f"restarted: {len(reached) - len(unit_failures)} of {len(reached)} activated nothing; in {all_but_commit} "
            "the sensor accepted every call but the COMMIT"
        )
    counts = Counter(t.outcome if t.outcome in ("old", "new") else "other" for t in trials)
    for t in trials:
        if t.outcome not in ("old", "new"):
            print(f"trial {t.index} ({t.how}): {t.outcome}")
    inside = Counter(t.outcome for t in trials if t.how.startswith("inside"))
    outside = Counter(t.outcome for t in trials if t.how.startswith("outside"))
    print(
        f"{len(trials)} power cuts: {counts['old']} old set, {counts['new']} new set, {counts['other']} other "
        f"(inside: {dict(inside)}; outside: {dict(outside)})"
    )
    replayed = [t for t in trials if t.replay]
    activated = [t for t in replayed if t.replay_outcome != "nothing activated"]
    for t in activated:
        print(f"trial {t.index}: replay of {t.replay}: {t.replay_outcome}")
    if replayed:
        kinds = Counter("whole" if t.replay.startswith("whole") else t.replay.split()[0] for t in replayed)
        kinds = {
            "whole": kinds["whole"],
            "prefix": kinds["prefix"],
            "frame subsets": len(replayed) - kinds["whole"] - kinds["prefix"],
        }
        acted = sum(t.replay_sessions > 0 for t in replayed)
        print(
            f"{len(replayed)} replays of recorded uploads {kinds}: {len(replayed) - len(activated)} activated nothing; "
            f"{acted} reached the sensor's staging (it opened a session for their STAGE_BEGIN)"
        )
    return 0 if counts["other"] == 0 and not activated and not unit_failures else 1


if __name__ == "__main__":
    sys.exit(main())
