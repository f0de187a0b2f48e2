"""Long-run fuzzing of every decoder (issue 15 acceptance: 10^6 inputs per decoder, 0 internal errors, 0 hangs, 0
corrupt inputs accepted). The short version runs in CI as tests/test_protocol_properties.py (hypothesis).

    python scripts/fuzz.py                       # 10^6 inputs per decoder
    python scripts/fuzz.py --n 100000 --decoders messages,serial

Each decoder gets random inputs and mutations of valid inputs (bit flips, dropped and inserted bytes):

* ``messages``: ``protocol.messages.decode`` of type-prefixed random bytes: only DecodeError; an accepted input must
  re-encode to itself (nothing else was taken for a message);
* ``serial``: ``protocol.framing.decode_frame`` of valid frames with 1-3 bits flipped or a byte dropped/inserted:
  only FramingError, never a frame accepted with other content;
* ``can_single``: ``protocol.can_frames.decode_single`` of random payloads: only CanDecodeError;
* ``can_stream``: the host's ``StreamAssembler`` on a valid stream with 1-3 bits flipped in its payloads: every
  delivered frame is exactly a sent one;
* ``isotp``: the host's ISO-TP channel on random frames: no internal error (what it assembles then goes to
  ``messages``);
* ``modbus_block``: ``protocol.modbus_map.block_intact`` of sealed blocks with 1-3 bits flipped: always refused
  (CRC-32 detects every error of up to 3 bits in blocks this short);
* ``param_table``: ``protocol.param_table.decode_table`` of random bytes: only TableError; an accepted table is the
  bytes bit for bit.

And every file reader, from its text (random and mutated valid files):

* ``param_json``: ``hostlink.files.params.params_with_sigma_from_text`` (what ``upload`` and every ``--nominal`` /
  ``--camera`` / ``--params`` reads) with and without validation, then the host's plausibility check: only UserError /
  ParameterError; a validated set is finite and rewrites to itself (random JSON, mutated files, huge and long
  numbers, NaN, wrong types, deep nesting);
* ``session_csv``: ``hostlink.files.session.read_session`` of mutated valid session CSVs (bytes flipped, lines
  dropped, duplicated or swapped, fields replaced by odd tokens, columns renamed): only UserError; an accepted
  session keeps every promise of the reader (:func:`session_promises_kept`).

One JSON line per decoder: inputs, internal errors (with the first one's text), corrupt accepted, hangs (inputs that
took longer than ``--hang-s``, interrupted by a timer), inputs that raised a Python warning (which the CLI would print
beside its one line; counted, not failed: an accepted odd date warns by design of ERFA), slowest input [s], inputs per
second. ``--max-s`` caps each
decoder's time (the line then says how many inputs it ran). Exit code 1 if any decoder has an internal error, a hang
or accepted corruption. The short version of the file readers' fuzzing is tests/test_files_fuzz_properties.py.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import atomic_open
from hostlink.files.params import load_params, params_from_text, params_json, params_with_sigma_from_text
from hostlink.files.session import Session, read_session
from hostlink.links.can_link import IsoTpChannel, StreamAssembler
from onboard.params import ParameterError, check_plausible
from onboard.prior import validate_sigma
from protocol import can_frames as cf
from protocol import messages as m
from protocol import modbus_map as mm
from protocol.framing import FramingError, decode_frame, encode_frame
from protocol.param_table import TABLE_BYTES, TableError, decode_table

_TYPES = np.array([s.type_id for s in m.MESSAGES], dtype=np.uint8)


def _mutate(rng: np.random.Generator, data: bytes) -> bytes:
    """1-3 flipped bits, or one byte dropped or inserted."""
    b = bytearray(data)
    kind = rng.integers(0, 4)
    if kind == 0 and b:
        del b[int(rng.integers(0, len(b)))]
    elif kind == 1:
        b.insert(int(rng.integers(0, len(b) + 1)), int(rng.integers(0, 256)))
    else:
        for bit in rng.choice(8 * len(b), size=min(int(rng.integers(1, 4)), 8 * len(b)), replace=False):
            b[bit // 8] ^= 1 << (bit % 8)
    return bytes(b)


def _random_message(rng: np.random.Generator) -> bytes:
    """A valid message's bytes: random bytes decoded until one decodes, else a fixed-size message of zeros."""
    spec = m.MESSAGES[int(rng.integers(0, len(m.MESSAGES)))]
    raw = bytes([spec.type_id]) + rng.integers(0, 256, spec.fixed_bytes - 1, dtype=np.uint8).tobytes()
    for f in spec.fields:  # zero the length fields: variable parts empty, the message valid
        if f.length_of is not None:
            offset = 1 + sum(x.element_bytes * x.count for x in spec.fields[: spec.fields.index(f)] if not x.variable)
            raw = raw[:offset] + bytes(f.element_bytes) + raw[offset + f.element_bytes :]
    try:
        return m.encode(m.decode(raw))
    except m.DecodeError:
        return m.encode(spec.cls(**({"frame": 1, "t_us": 0} if spec.cls is m.CentroidFrame else {})))


# ---------------------------------------------------------------------------------------------- decoders
def fuzz_messages(rng: np.random.Generator) -> bool:
    data = bytes([int(rng.choice(_TYPES))]) + rng.integers(0, 256, int(rng.integers(0, 160)), np.uint8).tobytes()
    if rng.random() < 0.5:
        data = _mutate(rng, _random_message(rng))
    try:
        msg = m.decode(data)
    except m.DecodeError:
        return True
    if any(f.fmt == "f" for f in m.spec_of(msg).fields):
        return len(m.encode(msg)) == len(data)  # float32 NaN payloads may be quietened on the way through Python
    return m.encode(msg) == data


def fuzz_serial(rng: np.random.Generator) -> bool:
    payload = _random_message(rng)
    wire = encode_frame(int(rng.integers(0, 65536)), payload)[:-1]
    bad = _mutate(rng, wire)
    if 0 in bad or bad == wire:
        return True  # a 0x00 splits the frame at a delimiter (each piece then decoded alone); a no-op mutation
    try:
        got = decode_frame(bad)
    except FramingError:
        return True
    return got.payload == payload  # only the same content may come out (never observed)


def fuzz_can_single(rng: np.random.Generator) -> bool:
    fid = int(rng.choice([cf.COMMAND.frame_id, cf.ACK.frame_id, cf.STAGE_FLOAT.frame_id, cf.COMMIT_BIND.frame_id]))
    data = rng.integers(0, 256, int(rng.integers(0, 10)), np.uint8).tobytes()
    try:
        cf.decode_single(fid, data)
    except cf.CanDecodeError:
        pass
    return True


def _stream_frame(rng: np.random.Generator, number: int) -> m.CentroidFrame:
    n = int(rng.integers(0, 20))
    return m.CentroidFrame(
        frame=number,
        t_us=1_773_454_200_000_000 + 100_000 * number,
        star_id=rng.integers(0, 1 << cf.STAR_ID_BITS, n).astype(np.uint32),
        x_px=rng.integers(0, 4096 * 1024, n) / 1024,
        y_px=rng.integers(0, 4096 * 1024, n) / 1024,
        mag=np.full(n, math.nan),
    )


def fuzz_can_stream(rng: np.random.Generator) -> bool:
    first = int(rng.integers(0, 2**32 - 4))
    frames = [_stream_frame(rng, first + k) for k in range(3)]
    enc = cf.StreamEncoder()
    wire = [pair for f in frames for pair in enc.encode(f)]
    for _ in range(int(rng.integers(1, 4))):
        i = int(rng.integers(0, len(wire)))
        fid, data = wire[i]
        wire[i] = (fid, _mutate(rng, data))
    asm = StreamAssembler()
    sent = {f.frame: f for f in frames}
    for fid, data in wire:
        out = asm.feed(fid, data)
        if isinstance(out, m.CentroidFrame) and not (out.frame in sent and out.same_as(sent[out.frame])):
            return False
    return True


_ISOTP = IsoTpChannel(lambda _msg: None, cf.ISOTP_HOST_TO_SENSOR_ID, cf.ISOTP_SENSOR_TO_HOST_ID)


def fuzz_isotp(rng: np.random.Generator) -> bool:
    chan = _ISOTP
    chan.reset()  # each input starts from an idle channel (one channel: constructing one costs ~5 ms)
    for _ in range(int(rng.integers(1, 12))):
        data = rng.integers(0, 256, int(rng.integers(0, 9)), np.uint8).tobytes()
        chan.feed(can.Message(arbitration_id=cf.ISOTP_SENSOR_TO_HOST_ID, data=data, is_extended_id=False))
        for payload in chan.poll():
            try:
                m.decode(payload)
            except m.DecodeError:
                pass
    return True


_MAP = mm.load_map()
_IMAGE_SIZE = _MAP.table_size("input")


def fuzz_modbus_block(rng: np.random.Generator) -> bool:
    block = _MAP.checked_blocks[int(rng.integers(0, len(_MAP.checked_blocks)))]
    image = [0] * _IMAGE_SIZE
    lo, count = block.read_span(0)
    image[lo : lo + count] = [int(v) for v in rng.integers(0, 65536, count)]
    if block.stars is not None:
        mm.put(image, block.stars, int(rng.integers(0, 256)))
        lo, count = block.read_span(mm.block_n_stars(block, image, 0))
        first_star = block.stars_from.address
        image[first_star : lo + count] = [int(v) for v in rng.integers(0, 65536, lo + count - first_star)]
    mm.seal_block(block, image)
    words = image[lo : lo + count]
    if not mm.block_intact(block, words, lo):
        return False
    for bit in rng.choice(16 * count, size=int(rng.integers(1, 4)), replace=False):
        words[bit // 16] ^= 1 << (bit % 16)
    return not mm.block_intact(block, words, lo)


def fuzz_param_table(rng: np.random.Generator) -> bool:
    n = TABLE_BYTES if rng.random() < 0.5 else int(rng.integers(0, 2 * TABLE_BYTES))
    data = rng.integers(0, 256, n, np.uint8).tobytes()
    try:
        values = decode_table(data)
    except TableError:
        return n != TABLE_BYTES
    return values.tobytes() == data


# ---------------------------------------------------------------------------------------------- file readers
def _valid_param_texts() -> list[str]:
    """Parameter files as users have them: the shipped nominal and camera, and a calibration result with a sigma."""
    camera = load_params("builtin:seed004_camera")
    sigma = {
        "focal_length_mm": 0.004,
        "principal_point_px": [0.3, None],
        "distortion": {"k1": 2e-11, "k2": 1e-16, "p1": 1e-8, "s2": 0.0},
    }
    result = params_json(camera, {"sigma": sigma, "method": "bundle", "rms_px": 0.05})
    texts = [json.dumps(params_json(load_params(n)), indent=2) for n in ("builtin:seed004_nominal",)]
    return [*texts, json.dumps(params_json(camera)), json.dumps(result, indent=1)]


_PARAM_TEXTS = _valid_param_texts()
_PARAM_OBJECTS = [json.loads(t) for t in _PARAM_TEXTS]
#: Values that break readers: huge, tiny, long, non-finite, of the wrong type, nested.
_ODD_JSON = [
    0, -1, 1, 2**63, -(2**64), 10**400, 1e308, -1e308, 5e-324, -0.0, math.nan, math.inf, -math.inf, True, False,
    None, "", "70", "NaN", "\u0000", "x" * 1000, [], [1], [1, 2, 3], [[1, 2]], ["a", "b"], {}, {"k1": 1},
    [1e308, 1e308], [-1, -1], [0, 0], [2**40, 2**40], [math.nan, 0],
]  # fmt: skip


def _random_json(rng: np.random.Generator, depth: int = 0) -> object:
    kind = int(rng.integers(0, 6 if depth < 6 else 3))
    if kind == 0:
        return _ODD_JSON[int(rng.integers(0, len(_ODD_JSON)))]
    if kind == 1:
        return float(rng.normal() * 10.0 ** int(rng.integers(-20, 20)))
    if kind == 2:
        return int(rng.integers(-(2**62), 2**62))
    if kind == 3:
        return [_random_json(rng, depth + 1) for _ in range(int(rng.integers(0, 4)))]
    keys = ["focal_length_mm", "pixel_pitch_um", "principal_point_px", "image_size_px", "distortion", "sigma", "k1"]
    return {str(rng.choice(keys)): _random_json(rng, depth + 1) for _ in range(int(rng.integers(0, 5)))}


def _replace_somewhere(rng: np.random.Generator, obj: object) -> object:
    """A copy of a JSON object with one value replaced, deleted or added at a random place."""
    if isinstance(obj, dict) and obj and rng.random() < 0.75:
        key = list(obj)[int(rng.integers(0, len(obj)))]
        out = dict(obj)
        op = rng.random()
        if op < 0.15:
            del out[key]
        elif op < 0.25:
            out["extra_" + str(int(rng.integers(0, 9)))] = _random_json(rng)
        elif op < 0.6 and isinstance(obj[key], (dict, list)):
            out[key] = _replace_somewhere(rng, obj[key])
        else:
            out[key] = _random_json(rng)
        return out
    if isinstance(obj, list) and obj and rng.random() < 0.75:
        out = list(obj)
        i = int(rng.integers(0, len(obj)))
        out[i] = _replace_somewhere(rng, obj[i]) if rng.random() < 0.3 else _random_json(rng)
        return out
    return _random_json(rng)


def param_text(rng: np.random.Generator) -> str:
    """A parameter-file text to read: a valid file with values replaced, or its bytes mutated; random JSON; deep
    nesting; an integer too long for Python to convert."""
    u = rng.random()
    if u < 0.45:
        obj = _PARAM_OBJECTS[int(rng.integers(0, len(_PARAM_OBJECTS)))]
        for _ in range(int(rng.integers(1, 4))):
            obj = _replace_somewhere(rng, obj)
        return json.dumps(obj, allow_nan=True)
    if u < 0.8:
        data = _PARAM_TEXTS[int(rng.integers(0, len(_PARAM_TEXTS)))].encode()
        for _ in range(int(rng.integers(1, 4))):
            data = _mutate(rng, data)
        return data.decode("utf-8", errors="replace")
    if u < 0.95:
        return json.dumps(_random_json(rng), allow_nan=True)
    depth = int(10 ** rng.uniform(1, 5.3))
    if rng.random() < 0.5:
        return str(rng.choice(["[", '{"a":', '{"distortion":'])) * depth
    return '{"focal_length_mm": 7' + "0" * depth + "}"


def param_text_handled(text: str, validate: bool) -> bool:
    """Read a parameter text as ``upload`` does, then check it as the host does before sending. Only UserError (the
    reader) or ParameterError (the check) may come out; False if a validated set is not finite or does not rewrite
    to itself (something other than the file was accepted). Any other exception propagates (an internal error)."""
    try:
        params, sigma = params_with_sigma_from_text(text, "fuzz", validate)
    except UserError:
        return True
    try:
        check_plausible(params, None)
        validate_sigma(sigma)
    except ParameterError:
        pass
    if not validate:
        return True
    values = [params.focal_length_mm, params.pixel_pitch_um, *params.principal_point_px, *params.image_size_px]
    if not all(math.isfinite(v) for v in values):
        return False
    again, _ = params_from_text(json.dumps(params_json(params)), "rewrite")
    return again == params


def fuzz_param_json(rng: np.random.Generator) -> bool:
    return param_text_handled(param_text(rng), validate=bool(rng.random() < 0.5))


def _valid_session_texts() -> list[str]:
    """Session files as the tools write them: identified stars with references, the same without time, and one with
    an unidentified star and an extra column (small, so a mutation hits a field that matters often)."""
    head = "frame,t_utc,star_id,x_px,y_px,mag,ra_deg,dec_deg\n"
    rows = [
        "0,2026-03-14T02:10:00.000Z,52419,628.117920,44.632277,2.654,160.9827124369,-64.5339068660",
        "0,2026-03-14T02:10:00.000Z,48002,120.568066,388.638041,3.019,146.9466362625,-65.1963187937",
        "0,2026-03-14T02:10:00.000Z,0,311.250000,901.500000,,,",
        "1,2026-03-14T02:10:01.000Z,52419,627.001200,45.100000,2.654,160.9827124369,-64.5339068660",
        "1,2026-03-14T02:10:01.000Z,50099,800.000000,500.250000,3.300,152.5000000000,-63.0000000000",
        "3,2026-03-14T02:10:03.000Z,48002,119.000000,390.000000,3.019,146.9466362625,-65.1963187937",
    ]
    full = head + "\n".join(rows) + "\n"
    untimed = full.replace("2026-03-14T02:10:00.000Z", "").replace("2026-03-14T02:10:01.000Z", "")
    untimed = untimed.replace("2026-03-14T02:10:03.000Z", "")
    bare = "frame,star_id,x_px,y_px,note\n" + "".join(
        f"{r.split(',')[0]},0,{k}.5,{k}.25,n{k}\n" for k, r in enumerate(rows)
    )
    return [full, untimed, bare]


_SESSION_TEXTS = _valid_session_texts()
_ODD_FIELDS = [
    "", " ", "nan", "NaN", "inf", "-inf", "1e400", "-1", "-0", "0x10", "1_000", "1e-400", "9" * 30, "9" * 5000,
    "abc", '"', '""', "\t", "2026-02-30T00:00:00Z", "2026-03-14T25:00:00Z", "2026-03-14", "1.5", "+3", "\x00",
    "frame", "2026-03-14T02:10:00.000Z",
]  # fmt: skip


def session_text(rng: np.random.Generator) -> str:
    """A session CSV to read: a valid one with lines dropped, duplicated or swapped, fields replaced by odd tokens,
    the header changed, or its bytes mutated."""
    text = _SESSION_TEXTS[int(rng.integers(0, len(_SESSION_TEXTS)))]
    for _ in range(int(rng.integers(1, 4))):
        lines = text.split("\n")
        op = int(rng.integers(0, 6))
        i, j = (int(v) for v in rng.integers(0, len(lines), 2))
        if op == 0:
            del lines[i]
        elif op == 1:
            lines.insert(i, lines[j])
        elif op == 2:
            lines[i], lines[j] = lines[j], lines[i]
        elif op in (3, 4):
            fields = lines[i].split(",")
            fields[int(rng.integers(0, len(fields)))] = str(rng.choice(_ODD_FIELDS))
            lines[i] = ",".join(fields)
        else:
            return _mutate(rng, text.encode()).decode("utf-8", errors="replace")
        text = "\n".join(lines)
    return text


def session_promises_kept(s: Session) -> bool:
    """What every consumer of ``read_session`` relies on: equal-length columns, frames in time order, integer star ids
    >= 0, finite centroids, a reference direction for every identified star (when the file has them), one time per
    frame that parses (when the time is known)."""
    n = len(s)
    cols = [s.frame, s.t_utc, s.star_id, s.x_px, s.y_px, *(c for c in (s.mag, s.ra_deg, s.dec_deg) if c is not None)]
    if any(len(c) != n for c in cols) or any(len(c) != n for c in s.extra.values()):
        return False
    if s.frame.dtype != np.int64 or s.star_id.dtype != np.int64 or np.any(np.diff(s.frame) < 0):
        return False
    if np.any(s.star_id < 0) or not (np.all(np.isfinite(s.x_px)) and np.all(np.isfinite(s.y_px))):
        return False
    if s.ra_deg is not None:
        known = s.star_id != 0
        if not (np.all(np.isfinite(s.ra_deg[known])) and np.all(np.isfinite(s.dec_deg[known]))):
            return False
    if n and s.time_known:
        jd1, jd2 = s.frame_times_jd()
        if not (np.all(np.isfinite(jd1)) and np.all(np.isfinite(jd2))):
            return False
    return True


def session_text_handled(text: str, path: Path) -> bool:
    """Write ``text`` to ``path`` and read it as every command does: only UserError may come out; False if an accepted
    session breaks a promise (:func:`session_promises_kept`). Any other exception propagates."""
    with atomic_open(path, binary=True, durable=False) as handle:  # scratch: never through a planted link
        handle.write(text.encode("utf-8", errors="surrogateescape"))
    try:
        session = read_session(path)
    except UserError:
        return True
    return session_promises_kept(session)


_SCRATCH = Path(tempfile.gettempdir() if not os.path.isdir("/dev/shm") else "/dev/shm") / f"fuzz-{os.getpid()}.csv"


def fuzz_session_csv(rng: np.random.Generator) -> bool:
    return session_text_handled(session_text(rng), _SCRATCH)


DECODERS: dict[str, Callable[[np.random.Generator], bool]] = {
    "messages": fuzz_messages,
    "serial": fuzz_serial,
    "can_single": fuzz_can_single,
    "can_stream": fuzz_can_stream,
    "isotp": fuzz_isotp,
    "modbus_block": fuzz_modbus_block,
    "param_table": fuzz_param_table,
    "param_json": fuzz_param_json,
    "session_csv": fuzz_session_csv,
}


class _Hang(BaseException):
    """Raised by the interval timer in an input that took longer than the hang limit (a BaseException, so that no
    ``except Exception`` in the code under test swallows it)."""


def _on_alarm(_signum, _frame) -> None:  # the signal handler signature
    raise _Hang


def run(name: str, n: int, seed: int, hang_s: float = 10.0, max_s: float = math.inf) -> dict:
    """Fuzz one decoder with ``n`` inputs (or for ``max_s`` seconds, whichever ends first). An input that takes more
    than ``hang_s`` is interrupted by a timer and counted as a hang."""
    rng = np.random.default_rng(seed)
    fn = DECODERS[name]
    internal, accepted, hangs, slowest, first_error = 0, 0, 0, 0.0, ""
    warned, first_warning = 0, ""
    signal.signal(signal.SIGALRM, _on_alarm)
    t_start = time.perf_counter()
    done = 0
    while done < n and time.perf_counter() - t_start < max_s:
        t0 = time.perf_counter()
        signal.setitimer(signal.ITIMER_REAL, hang_s)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                ok = fn(rng)
            if caught:  # the CLI would print it on stderr beside its one line
                warned += 1
                first_warning = first_warning or f"{caught[0].category.__name__}: {caught[0].message}"[:300]
        except _Hang:
            hangs += 1
            ok = True
        except Exception as exc:  # noqa: BLE001 - counting internal errors is the point
            internal += 1
            first_error = first_error or f"{type(exc).__name__}: {exc}"[:300]
            ok = True
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        accepted += not ok
        done += 1
        slowest = max(slowest, time.perf_counter() - t0)
    elapsed = time.perf_counter() - t_start
    return {
        "decoder": name,
        "inputs": done,
        "internal_errors": internal,
        "first_internal_error": first_error,
        "corrupt_accepted": accepted,
        "hangs": hangs,
        "inputs_with_warnings": warned,
        "first_warning": first_warning,
        "slowest_input_s": round(slowest, 4),
        "inputs_per_s": round(done / elapsed),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000, help="inputs per decoder (default 10^6)")
    parser.add_argument("--decoders", default=",".join(DECODERS), help=f"comma-separated, of: {', '.join(DECODERS)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hang-s", type=float, default=10.0, help="an input taking longer is a hang (default 10 s)")
    parser.add_argument("--max-s", type=float, default=math.inf, help="most seconds per decoder (default: no limit)")
    args = parser.parse_args()
    bad = False
    try:
        for name in args.decoders.split(","):
            if name not in DECODERS:
                parser.error(f"unknown decoder {name!r}")
            result = run(name, args.n, args.seed, args.hang_s, args.max_s)
            bad |= bool(result["internal_errors"] or result["corrupt_accepted"] or result["hangs"])
            print(json.dumps(result), flush=True)
    finally:
        _SCRATCH.unlink(missing_ok=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
