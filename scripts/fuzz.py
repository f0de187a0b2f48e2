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

One JSON line per decoder: inputs, internal errors (with the first one's text), corrupt accepted, slowest input [s]
(a hang would show there), inputs per second. Exit code 1 if any decoder has an internal error or accepted corruption.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable

import can
import numpy as np

from hostlink.links.can_link import IsoTpChannel, StreamAssembler
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


def fuzz_isotp(rng: np.random.Generator) -> bool:
    chan = IsoTpChannel(lambda _msg: None, cf.ISOTP_HOST_TO_SENSOR_ID, cf.ISOTP_SENSOR_TO_HOST_ID)
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


DECODERS: dict[str, Callable[[np.random.Generator], bool]] = {
    "messages": fuzz_messages,
    "serial": fuzz_serial,
    "can_single": fuzz_can_single,
    "can_stream": fuzz_can_stream,
    "isotp": fuzz_isotp,
    "modbus_block": fuzz_modbus_block,
    "param_table": fuzz_param_table,
}


def run(name: str, n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    fn = DECODERS[name]
    internal, accepted, slowest, first_error = 0, 0, 0.0, ""
    t_start = time.perf_counter()
    for _ in range(n):
        t0 = time.perf_counter()
        try:
            ok = fn(rng)
        except Exception as exc:  # noqa: BLE001 - counting internal errors is the point
            internal += 1
            first_error = first_error or f"{type(exc).__name__}: {exc}"
            ok = True
        accepted += not ok
        slowest = max(slowest, time.perf_counter() - t0)
    elapsed = time.perf_counter() - t_start
    return {
        "decoder": name,
        "inputs": n,
        "internal_errors": internal,
        "first_internal_error": first_error,
        "corrupt_accepted": accepted,
        "slowest_input_s": round(slowest, 4),
        "inputs_per_s": round(n / elapsed),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000, help="inputs per decoder (default 10^6)")
    parser.add_argument("--decoders", default=",".join(DECODERS), help=f"comma-separated, of: {', '.join(DECODERS)}")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    bad = False
    for name in args.decoders.split(","):
        if name not in DECODERS:
            parser.error(f"unknown decoder {name!r}")
        result = run(name, args.n, args.seed)
        bad |= bool(result["internal_errors"] or result["corrupt_accepted"])
        print(json.dumps(result), flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
