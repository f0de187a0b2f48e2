"""The generated C (``hostlink export-c``) compiles warning-free as C99 and agrees with the Python protocol byte for
byte: every message type round-trips both ways, malformed messages are refused exactly when Python refuses them,
COBS/serial frames and CRCs match, and the CAN signal positions unpack what ``protocol.can_frames`` packs.

One compile and one run of a small driver program carry every check (a few seconds)."""

from __future__ import annotations

import math
import shutil
import struct
import subprocess
import zlib

import numpy as np
import pytest
from cobs import cobs

from hostlink.portkit import export_c
from hostlink.portkit.export_c import c_name
from protocol import can_frames, framing, messages
from protocol.crc import crc16_ccitt, crc32
from protocol.messages import MESSAGES, DecodeError, decode, encode
from protocol.param_table import TABLE_BYTES, table_crc

CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc) on this machine")

_INT_RANGE = {
    "B": (0, 255),
    "H": (0, 65535),
    "h": (-32768, 32767),
    "I": (0, 2**32 - 1),
    "i": (-(2**31), 2**31 - 1),
    "q": (-(2**63), 2**63 - 1),
}
_C_INT = {"B": "uint8_t", "H": "uint16_t", "h": "int16_t", "I": "uint32_t", "i": "int32_t", "q": "int64_t"}

_DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "st_can.h"
#include "st_messages.h"
#include "st_param_table.h"
#include "st_wire.h"

static char line[1 << 16];
static uint8_t in[1 << 15], out[1 << 15], work[1 << 15];
static st_message_t msg;

static size_t unhex(const char *s, uint8_t *dst)
{
    size_t n = 0u;
    while (s[0] && s[1] && s[0] != '\n') {
        unsigned v;
        sscanf(s, "%2x", &v);
        dst[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}
static void puthex(const uint8_t *p, size_t n)
{
    size_t i;
    for (i = 0u; i < n; ++i) printf("%02x", p[i]);
}
static float f32_bits(uint32_t bits)
{
    uint8_t b[4];
    st_put_u32(b, bits);
    return st_get_f32(b);
}

FILL_FUNCTIONS

static void can_unpack(unsigned id, uint64_t w)
{
    uint64_t again = 0u;
    switch (id) {
CAN_CASES
    default: printf("E unknown id\n"); return;
    }
    printf(" R %016llx\n", (unsigned long long)again);
}

int main(void)
{
    while (fgets(line, sizeof line, stdin)) {
        char op = line[0];
        const char *arg = line[1] == ' ' ? line + 2 : line + 1;
        size_t n, m;
        int rc;
        if (op == 'D') { /* decode a message, re-encode it */
            n = unhex(arg, in);
            rc = st_decode(in, n, &msg);
            if (rc != ST_OK) { printf("E %d\n", rc); continue; }
            m = st_encode(&msg, out, sizeof out);
            printf("O "); puthex(out, m); printf("\n");
        } else if (op == 'N') { /* encode sample k from its fields */
            int k = atoi(arg);
            memset(&msg, 0, sizeof msg);
            fill(k, &msg);
            m = st_encode(&msg, out, sizeof out);
            printf("O "); puthex(out, m); printf("\n");
        } else if (op == 'F') { /* frame a payload: F seq hex */
            char *rest;
            unsigned long seq = strtoul(arg, &rest, 10);
            n = unhex(rest + 1, in);
            m = st_frame_encode((uint16_t)seq, in, n, work, out, sizeof out);
            printf("O "); puthex(out, m); printf("\n");
        } else if (op == 'U') { /* unframe (no delimiter) */
            uint16_t seq;
            n = unhex(arg, in);
            rc = st_frame_decode(in, n, work, &seq, out, sizeof out, &m);
            if (rc != ST_OK) { printf("E %d\n", rc); continue; }
            printf("S %u ", (unsigned)seq); puthex(out, m); printf("\n");
        } else if (op == 'K') {
            n = unhex(arg, in);
            m = st_cobs_encode(in, n, out, sizeof out);
            printf("O "); puthex(out, m); printf("\n");
        } else if (op == 'k') {
            n = unhex(arg, in);
            rc = st_cobs_decode(in, n, out, sizeof out, &m);
            if (rc != ST_OK) { printf("E %d\n", rc); continue; }
            printf("O "); puthex(out, m); printf("\n");
        } else if (op == 'C') {
            n = unhex(arg, in);
            printf("O %08lx %04x\n", (unsigned long)st_crc32(in, n), (unsigned)st_crc16_ccitt(in, n));
        } else if (op == 'T') { /* parameter table: decode to floats, encode again, CRC */
            float values[ST_PARAM_N_FIELDS];
            unhex(arg, in);
            st_param_table_decode(in, values);
            st_param_table_encode(values, out);
            printf("O "); puthex(out, ST_PARAM_TABLE_BYTES);
            printf(" %08lx\n", (unsigned long)st_param_table_crc(in));
        } else if (op == 'W') { /* CAN: W id hex8 */
            char *rest;
            unsigned long id = strtoul(arg, &rest, 10);
            unhex(rest + 1, in);
            printf("O");
            can_unpack((unsigned)id, st_can_word(in));
        }
        fflush(stdout);
    }
    return 0;
}
"""


# ------------------------------------------------------------------------------------------------- samples
def _c_int(value: int, fmt: str) -> str:
    lo, _ = _INT_RANGE[fmt]
    if value == lo and lo < 0:
        return f"(({_C_INT[fmt]})({lo + 1}LL) - 1)"
    suffix = "ULL" if value >= 0 else "LL"
    return f"(({_C_INT[fmt]}){value}{suffix})"


def _c_float(value: float) -> str:
    (bits,) = struct.unpack("<I", struct.pack("<f", value))
    return f"f32_bits(0x{bits:08X}u)"


class _Sample:
    """A message built from wire values (what the C fills in) and the Python message made of the same values."""

    def __init__(self, spec: messages.MessageSpec, values: dict) -> None:
        self.spec = spec
        self.values = values  # field name -> wire value (ints, float32 floats, bytes, record steps dict)
        kwargs = {}
        for f in spec.fields:
            if f.length_of is not None:
                continue
            v = values[f.name]
            if f.fmt == "record":
                for m in f.record:
                    col = np.asarray(v[m.name], dtype=np.int64)
                    if m.fixed is None:
                        kwargs[m.name] = col.astype(np.uint32)
                    else:
                        phys = col / m.fixed.steps_per_unit
                        if m.fixed.absent is not None:
                            phys = np.where(col == m.fixed.absent, np.nan, phys)
                        kwargs[m.name] = phys
            elif f.fmt == "s" and f.text:
                kwargs[f.name] = v.decode("utf-8")
            elif f.fmt == "?":
                kwargs[f.name] = bool(v)
            else:
                kwargs[f.name] = v
        self.message = spec.cls(**kwargs)

    def c_fill(self) -> list[str]:
        n = c_name(self.spec.name)
        out = [f"m->type = ST_MSG_{self.spec.name};"]
        for f in self.spec.fields:
            target = f"m->u.{n}.{c_name(f.name)}"
            if f.length_of is not None:
                out.append(f"{target} = {len(_elements_of(self.values[f.length_of]))};")
                continue
            v = self.values[f.name]
            if f.fmt == "record":
                count = len(v[f.record[0].name])
                for k in range(count):
                    for m in f.record:
                        out.append(f"{target}[{k}].{c_name(m.name)} = {_c_int(int(v[m.name][k]), m.fmt)};")
            elif f.fmt == "s":
                out += [f"{target}[{k}] = {b}u;" for k, b in enumerate(v)]
            elif f.fmt == "f":
                vals = v if isinstance(v, tuple) else (v,)
                out += [f"{target}[{k}] = {_c_float(x)};" for k, x in enumerate(vals)]
            elif f.fmt == "?":
                out.append(f"{target} = {int(bool(v))}u;")
            else:
                out.append(f"{target} = {_c_int(int(v), f.fmt)};")
        return out


def _elements_of(value) -> list:
    if isinstance(value, dict):
        return list(next(iter(value.values())))
    return list(value)


def _random_values(spec: messages.MessageSpec, rng: np.random.Generator, mode: str) -> dict:
    """Wire values of every field: mode 'random', 'max' (extremes, longest variable fields) or 'empty'."""
    values: dict = {}
    for f in spec.fields:
        if f.length_of is not None:
            continue
        if f.fmt == "record":
            n = {"random": int(rng.integers(1, 40)), "max": f.max_count, "empty": 0}[mode]
            rec = {}
            for m in f.record:
                lo, hi = _INT_RANGE[m.fmt]
                if m.fixed is not None and m.fixed.absent is not None:
                    lo = m.fixed.absent  # the absent marker itself, and every representable value
                if mode == "max":
                    col = np.resize(np.array([lo, hi, 0, -1 if lo < 0 else 1], dtype=np.int64), n)
                else:
                    col = rng.integers(lo, hi, size=n, endpoint=True, dtype=np.int64)
                rec[m.name] = col
            values[f.name] = rec
        elif f.fmt == "s" and f.text:
            texts = {
                "random": "principal_point_px[0]: 5000.0 is off the detector [-0.5, 2047.5] (µ, °, €, 😀)",
                "max": "é" * (f.max_count // 2) + "a" * (f.max_count % 2),  # exactly max_count bytes
                "empty": "",
            }
            values[f.name] = messages.nak_text_bytes(texts[mode])
        elif f.fmt == "s":
            n = int(f.count) if not f.variable else {"random": 37, "max": f.max_count, "empty": 0}[mode]
            values[f.name] = bytes(rng.integers(0, 256, size=n, dtype=np.int64).tolist())
        elif f.fmt == "f":
            specials = [math.nan, math.inf, -math.inf, -0.0, 1e-45, 3.4028234663852886e38, 70.2262, -1.5e-9]
            count = int(f.count)
            if mode == "random":
                vals = [float(np.float32(x)) for x in rng.normal(0, 100, size=count)]
            else:
                vals = [float(np.float32(specials[k % len(specials)])) for k in range(count)]
            values[f.name] = tuple(vals) if count != 1 else vals[0]
        elif f.fmt == "?":
            values[f.name] = mode != "empty"
        else:
            lo, hi = _INT_RANGE[f.fmt]
            values[f.name] = {"random": int(rng.integers(lo, hi, endpoint=True)), "max": hi, "empty": lo}[mode]
    return values


def _samples() -> list[_Sample]:
    rng = np.random.default_rng(14)
    out = []
    for spec in MESSAGES:
        for mode in ("random", "max", "empty"):
            out.append(_Sample(spec, _random_values(spec, rng, mode)))
    return out


def _fill_functions(samples: list[_Sample]) -> str:
    lines = []
    for k, s in enumerate(samples):
        lines.append(f"static void fill_{k}(st_message_t *m)")
        lines.append("{")
        lines += [f"    {x}" for x in s.c_fill()]
        lines.append("}")
    lines.append("static void fill(int k, st_message_t *m)")
    lines.append("{")
    lines.append("    switch (k) {")
    lines += [f"    case {k}: fill_{k}(m); break;" for k in range(len(samples))]
    lines += ["    default: break;", "    }", "}"]
    return "\n".join(lines)


def _can_cases() -> str:
    lines = []
    for msg in can_frames.CAN_MESSAGES:
        lines.append(f"    case ST_CAN_{msg.name}_ID:")
        for sig in msg.signals:
            base = f"ST_CAN_{msg.name}_{sig.name.upper()}"
            get = f"st_can_get(w, {base}_START, {base}_BITS)"
            lines.append(f'        printf(" %llu", (unsigned long long){get});')
            lines.append(f"        again = st_can_set(again, {base}_START, {base}_BITS, {get});")
        lines.append("        break;")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------- fixture
@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    """The exported C compiled with the driver: (run(lines) -> output lines, samples)."""
    directory = tmp_path_factory.mktemp("c")
    export_c.write_c(directory)
    samples = _samples()
    driver = _DRIVER.replace("FILL_FUNCTIONS", _fill_functions(samples)).replace("CAN_CASES", _can_cases())
    (directory / "driver.c").write_text(driver)
    exe = directory / "driver"
    # the generated source must compile clean under the strictest common flags; the driver (test code) too
    cmd = [CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1", "-o", str(exe)]
    result = subprocess.run(
        [*cmd, str(directory / "st_protocol.c"), str(directory / "driver.c")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr

    def run(lines: list[str]) -> list[str]:
        proc = subprocess.run([str(exe)], input="\n".join(lines) + "\n", capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        out = proc.stdout.splitlines()
        assert len(out) == len(lines)
        return out

    return run, samples


def _nan_equal(a, b) -> bool:
    if isinstance(a, (np.ndarray, tuple, list)):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=np.asarray(a).dtype.kind == "f")
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return a == b


def _same_message(a, b) -> bool:
    return type(a) is type(b) and all(_nan_equal(getattr(a, name), getattr(b, name)) for name in a.__dataclass_fields__)


# ----------------------------------------------------------------------------------------------------- tests
def test_generated_c_covers_every_message_type_of_the_table(kit):
    _, samples = kit
    assert {s.spec.name for s in samples} == {s.name for s in MESSAGES}
    header = export_c.generate_c()["st_messages.h"]
    for spec in MESSAGES:
        assert f"ST_MSG_{spec.name} = 0x{spec.type_id:02X}," in header


def test_c_decodes_and_reencodes_python_messages_byte_for_byte(kit):
    run, samples = kit
    wires = [encode(s.message) for s in samples]
    out = run([f"D {w.hex()}" for w in wires])
    for s, w, line in zip(samples, wires, out, strict=True):
        assert line == f"O {w.hex()}", s.spec.name


def test_c_encoded_messages_from_fields_decode_in_python_to_the_same_message(kit):
    run, samples = kit
    out = run([f"N {k}" for k in range(len(samples))])
    for s, line in zip(samples, out, strict=True):
        assert line.startswith("O "), s.spec.name
        data = bytes.fromhex(line[2:])
        assert data == encode(s.message), s.spec.name
        assert _same_message(decode(data), s.message), s.spec.name


def _mutations(data: bytes, spec: messages.MessageSpec, rng: np.random.Generator) -> list[bytes]:
    out = [data[:-1], data + b"\x00", data[:1]]
    for _ in range(4):
        k = int(rng.integers(0, len(data)))
        out.append(data[:k] + bytes([int(rng.integers(0, 256))]) + data[k + 1 :])
    pos = 1
    for f in spec.fields:  # each length field one above its maximum, each boolean byte 2
        size = struct.calcsize("<" + f.fmt) if f.fmt in "BH?" else 0
        if f.length_of is not None:
            target = next(x for x in spec.fields if x.name == f.length_of)
            out.append(
                data[:pos]
                + struct.pack("<" + f.fmt, min(target.max_count + 1, _INT_RANGE[f.fmt][1]))
                + data[pos + size :]
            )
        if f.fmt == "?":
            out.append(data[:pos] + b"\x02" + data[pos + 1 :])
        if f.variable or f.fmt == "record":
            break
        pos += f.element_bytes * int(f.count) if isinstance(f.count, int) else 0
    return out


def test_c_refuses_exactly_the_malformed_messages_python_refuses(kit):
    run, samples = kit
    rng = np.random.default_rng(15)
    cases = [b"", bytes([0x7F]), bytes([messages.MsgType.GET_STATUS])]
    for s in samples:
        cases += _mutations(encode(s.message), s.spec, rng)
    nak = encode(messages.Nak(tag=1, command=4, code=5, text="ok"))
    for bad_text in (b"\xc0\x80", b"\xed\xa0\x80", b"\xf4\x90\x80\x80", b"\xe2\x82", b"\xff", b"\x80"):
        cases.append(nak[:5] + bytes([len(bad_text)]) + bad_text)  # overlong, surrogate, > U+10FFFF, cut, bad byte
    out = run([f"D {c.hex()}" for c in cases])
    refused = 0
    for c, line in zip(cases, out, strict=True):
        try:
            decode(c)
            python_ok = True
        except DecodeError:
            python_ok = False
        if python_ok:
            assert line == f"O {c.hex()}", c.hex()  # accepted, and bit-exact (the C keeps every float's bits)
        else:
            assert line.startswith("E "), c.hex()
            refused += 1
    assert refused >= len(cases) // 2  # the mutations do exercise the refusals


def test_c_cobs_matches_the_python_cobs_package_both_ways(kit):
    run, _ = kit
    rng = np.random.default_rng(16)
    raw = [
        b"",
        b"\x00",
        b"\x00\x00",
        b"\x01" * 253,
        b"\x01" * 254,
        b"\x01" * 255,
        b"\x01" * 508,
        b"\x01" * 254 + b"\x00",
    ]
    raw += [bytes(rng.integers(0, 4 if k % 2 else 256, size=int(rng.integers(0, 700))).tolist()) for k in range(60)]
    out = run([f"K {r.hex()}" for r in raw])
    for r, line in zip(raw, out, strict=True):
        assert line == f"O {cobs.encode(r).hex()}", r.hex()
    encoded = [cobs.encode(r) for r in raw]
    encoded += [e[:-1] for e in encoded if len(e) > 1]  # truncated groups
    encoded += [bytes(rng.integers(0, 8, size=int(rng.integers(1, 40))).tolist()) for _ in range(60)]
    out = run([f"k {e.hex()}" for e in encoded])
    for e, line in zip(encoded, out, strict=True):
        try:
            expected = f"O {cobs.decode(e).hex()}"
        except cobs.DecodeError:
            expected = "E"
        assert line.startswith("E") if expected == "E" else line == expected, e.hex()


def test_c_serial_frames_match_protocol_framing(kit):
    run, samples = kit
    payloads = [encode(s.message) for s in samples]
    seqs = [(7919 * k) % framing.SEQ_MODULUS for k in range(len(payloads))]
    out = run([f"F {q} {p.hex()}" for q, p in zip(seqs, payloads, strict=True)])
    frames = [framing.encode_frame(q, p) for q, p in zip(seqs, payloads, strict=True)]
    for f, line in zip(frames, out, strict=True):
        assert line == f"O {f.hex()}"
    rng = np.random.default_rng(17)
    wires = [f[:-1] for f in frames]  # without the delimiter, as decode_frame takes them
    for f in list(wires):
        k = int(rng.integers(0, len(f)))
        wires.append(f[:k] + bytes([(f[k] ^ (1 << int(rng.integers(0, 8)))) or 1]) + f[k + 1 :])  # one bit flipped
    wires += [cobs.encode(b"\x01\x02\x03"), b""]  # too short to hold seq and CRC
    out = run([f"U {w.hex()}" for w in wires])
    for w, line in zip(wires, out, strict=True):
        try:
            fr = framing.decode_frame(w)
            assert line == f"S {fr.seq} {fr.payload.hex()}"
        except framing.FramingError:
            assert line.startswith("E "), w.hex()


def test_c_crcs_and_parameter_table_match_python(kit):
    run, _ = kit
    rng = np.random.default_rng(18)
    data = [b"123456789", b""] + [bytes(rng.integers(0, 256, size=n).tolist()) for n in (1, 7, 92, 255, 3000)]
    out = run([f"C {d.hex()}" for d in data])
    for d, line in zip(data, out, strict=True):
        assert line == f"O {crc32(d):08x} {crc16_ccitt(d):04x}"
    assert export_c.crc32_by_table(b"123456789") == zlib.crc32(b"123456789") == 0xCBF43926
    tables = [bytes(rng.integers(0, 256, size=TABLE_BYTES).tolist()) for _ in range(5)]
    tables.append(np.arange(TABLE_BYTES // 4, dtype="<f4").tobytes())
    out = run([f"T {t.hex()}" for t in tables])
    for t, line in zip(tables, out, strict=True):
        assert line == f"O {t.hex()} {table_crc(t):08x}"


def test_c_can_signal_positions_unpack_what_protocol_can_frames_packs(kit):
    run, _ = kit
    rng = np.random.default_rng(19)
    n = 20
    frame = messages.CentroidFrame(
        frame=123457,
        t_us=1_780_000_000_123_456,
        star_id=rng.integers(0, 1 << 17, size=n).astype(np.uint32),
        x_px=rng.integers(-512 * 1024, 7679 * 1024, size=n) / 1024.0,
        y_px=rng.integers(-512 * 1024, 7679 * 1024, size=n) / 1024.0,
        mag=np.full(n, np.nan),
    )
    frames, _ = can_frames.encode_stream_frame(frame, None)
    frames.append(can_frames.encode_single(messages.StageVerify(tag=77, crc32=0xDEADBEEF)))
    frames.append(can_frames.encode_single(messages.Ack(tag=65535, command=7, value=42)))
    frames.append((can_frames.COMMIT_BIND.frame_id, can_frames.encode_commit_bind(0xFFFFFFFF, 3)))
    frames.append((can_frames.STAGE_FLOAT.frame_id, can_frames.encode_stage_float(9, 22, -1.25)))
    frames.append((can_frames.END_OF_STREAM.frame_id, can_frames.encode_end_of_stream(70000, 69999)))
    assert {i for i, _ in frames} == {m.frame_id for m in can_frames.CAN_MESSAGES}
    out = run([f"W {i} {p.hex()}" for i, p in frames])
    for (i, payload), line in zip(frames, out, strict=True):
        msg = can_frames.MESSAGES_BY_ID[i]
        word = int.from_bytes(payload, "little")
        raw = can_frames.unpack(msg, np.uint64(word))
        expected = " ".join(str(int(raw[s.name])) for s in msg.signals)
        assert line == f"O {expected} R {word:016x}", msg.name  # every payload bit belongs to a signal
