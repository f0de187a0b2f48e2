"""The Python firmware and the C firmware core side by side (tests/test_firmware_c.py, scripts/firmware_c_proof.py):
the same device identity, the same factory set, each with its own RAM flash; every command goes to both, and the
replies and the flash images are compared byte for byte.

A step is four integers (kind, a, b, c) that :meth:`Twins.step` reads as a command or an event (reboot, power cut),
so hypothesis (or a seeded generator) draws sequences of them and shrinks a failing one to its shortest form."""

from __future__ import annotations

import math
import struct

import numpy as np

from hostlink.portkit.firmware_c import CFirmware
from onboard import banks
from onboard.firmware import Firmware
from onboard.params import CameraParams, Distortion, PlausibilityLimits
from protocol import messages as m
from protocol.crc import crc32
from protocol.param_table import TABLE_BYTES

NOMINAL = CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024))
LIMITS = PlausibilityLimits(70.0)
N_FIELDS = TABLE_BYTES // 4
#: Values a table field is set to by a step: the edges of every rule (zero, signs, NaN, infinities, whole and
#: half pixels, huge and tiny magnitudes, the image-size bound, values a distortion refusal turns into text).
SPECIAL_VALUES = (
    0.0, -0.0, 1.0, -1.0, 0.5, 1024.5, math.nan, math.inf, -math.inf, 3e38, -3e38, 1e-30, 1e-45, 16777216.0,
    16777217.0, 2e7, 70.1, 73.6, 80.0, 12.0, 1e-9, -1e-9, 1e-6, -1e-6, 1e-12, 5000.0, -0.75, 1023.5, 1023.6, 0.1,
)  # fmt: skip


def _tables() -> list[bytes]:
    """Good sets (several distortions, with and without a sigma) and sets breaking each rule."""
    sigma = np.array([0.05, 2.0, 2.0, 1e-10, 1e-15, np.nan, 0, 0, 1e-7, 0])
    good = [
        banks.params_to_table(NOMINAL),
        banks.params_to_table(CameraParams(70.3, 12.0, (505.25, 520.5), (1024, 1024), Distortion(k1=-1e-9))),
        banks.params_to_table(CameraParams(69.8, 12.0, (511.5, 511.5), (1024, 1024), Distortion(k2=2e-15)), sigma),
        banks.params_to_table(
            CameraParams(70.0, 12.0, (500.0, 530.0), (1024, 768), Distortion(-1e-9, 1e-16, 0, 1e-7, -1e-7, 2e-7))
        ),
    ]
    bad = [
        banks.params_to_table(CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024), Distortion(k1=5e-6))),
        banks.params_to_table(CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024), Distortion(k1=-3e-7))),
        banks.params_to_table(CameraParams(70.0, 12.0, (511.5, 511.5), (1024, 1024), Distortion(p1=4e-4, s1=-9e-4))),
        banks.params_to_table(CameraParams(77.0, 12.0, (511.5, 511.5), (1024, 1024))),
        banks.params_to_table(NOMINAL, np.array([0.05, -1.0, 2, 0, 0, 0, 0, 0, 0, 0])),
    ]
    return good + bad


TABLES = _tables()
#: The C library the twins load (None: the ordinary build, ``firmware_c.load_library()``; the sanitized one for
#: ``scripts/firmware_c_proof.py --sanitize``).
LIBRARY = None


def with_field(table: bytes, index: int, value: float) -> bytes:
    """``table`` with float32 field ``index`` set to ``value``."""
    out = bytearray(table)
    struct.pack_into("<f", out, 4 * index, value)
    return bytes(out)


def _not_commands(tag: int, a: int) -> list[m.Message]:
    return [
        m.Ack(tag=tag, command=3, value=a),
        m.Nak(tag=tag, command=7, code=10, text="replayed"),
        m.Telemetry(tag=tag),
        m.ParamTable(tag=tag, table=TABLES[0]),
        m.Estimate(tag=tag, values=(0.0,) * 10, sigma=(0.0,) * 10),
        m.CentroidFrame(
            frame=a, t_us=1, star_id=np.array([1], np.uint32), x_px=np.array([1.0]), y_px=np.array([2.0]),
            mag=np.array([np.nan]),
        ),
        m.EndOfStream(frames_sent=a),
    ]  # fmt: skip


class Twins:
    """A Python and a C sensor of one device identity (``seed``), factory set NOMINAL in a fresh RAM flash each
    (``image``: boot both from a copy of this flash image instead)."""

    def __init__(self, seed: int, image: np.ndarray | None = None) -> None:
        self.py_identity = banks.seeded_identity(seed)
        self.c_identity = banks.seeded_identity(seed)
        if image is None:
            self.py = Firmware(banks.factory_store(NOMINAL, banks.RamFlash(), LIMITS, self.py_identity))
            self.c = CFirmware(
                banks.RamFlash(), self.c_identity, LIMITS, factory=NOMINAL, with_estimator=False, library=LIBRARY
            )
        else:
            self.py = Firmware(banks.boot(banks.RamFlash(image.copy()), LIMITS, self.py_identity))
            self.c = CFirmware(
                banks.RamFlash(image.copy()), self.c_identity, LIMITS, with_estimator=False, library=LIBRARY
            )
        self.table = TABLES[0]
        self.nonce = 0
        self.steps = 0
        self.refusals: dict[int, int] = {}  # NAK code -> count (what the sequences exercised)
        self.commits = 0

    # ------------------------------------------------------------------------------------------ one message
    def send(self, data: bytes) -> bytes | None:
        """Both firmwares take ``data``; their replies must be the same bytes. Returns the reply (None = no reply,
        the bytes are not a message)."""
        try:
            py_reply = m.encode(self.py.handle(m.decode(data)))
        except m.DecodeError:
            py_reply = None
        c_reply = self.c.handle_bytes(data)
        assert c_reply == py_reply, f"after {self.steps} steps, command {data.hex()}:\n py {py_reply}\n  c {c_reply}"
        if py_reply is not None:
            reply = m.decode(py_reply)
            if isinstance(reply, m.Nak):
                self.refusals[reply.code] = self.refusals.get(reply.code, 0) + 1
            if isinstance(reply, m.Ack) and reply.command == m.MsgType.STAGE_BEGIN:
                self.nonce = reply.value
            if isinstance(reply, m.Ack) and reply.command == m.MsgType.COMMIT:
                self.commits += 1
        return py_reply

    def command(self, message: m.Message) -> bytes | None:
        return self.send(m.encode(message))

    def check_flash(self) -> None:
        py_image = self.py.store.flash.image
        c_image = self.c.flash.image
        assert np.array_equal(py_image, c_image), f"flash differs after {self.steps} steps at " + str(
            np.flatnonzero(py_image != c_image)[:8]
        )

    def reboot(self) -> None:
        """Power cycle both (RAM lost, flash kept, the same device)."""
        self.py = Firmware(banks.boot(banks.RamFlash(self.py.store.flash.image.copy()), LIMITS, self.py_identity))
        self.c = CFirmware(
            banks.RamFlash(self.c.flash.image.copy()), self.c_identity, LIMITS, with_estimator=False, library=LIBRARY
        )

    def power_cut(self, budget: int, message: m.Message) -> None:
        """``message`` with the power failing after ``budget`` flash bytes: both stop at the same byte (or both
        complete), then both reboot."""
        self.py.store.flash.power_budget = budget
        self.c.flash.power_budget = budget
        outcome = []
        for handle in (lambda: self.py.handle(message), lambda: self.c.handle_bytes(m.encode(message))):
            try:
                handle()
                outcome.append("done")
            except banks.PowerCut:
                outcome.append("cut")
        assert outcome[0] == outcome[1], f"power cut after {budget} bytes: python {outcome[0]}, c {outcome[1]}"
        self.py.store.flash.power_budget = None
        self.c.flash.power_budget = None
        self.check_flash()
        self.reboot()

    def exposure(self, counter: int) -> None:
        """Both count one exposure with frame counter ``counter`` (no catalogue: no estimator run)."""
        frame = m.CentroidFrame(
            frame=counter, t_us=counter, star_id=np.array([1], np.uint32), x_px=np.array([1.0]),
            y_px=np.array([2.0]), mag=np.array([np.nan]),
        )  # fmt: skip
        assert self.py.process_frame(frame, None) == self.c.process_frame(frame, None)

    def cross_boot(self, seed: int) -> int:
        """The Python firmware's flash image booted by a C sensor and the C firmware's by a Python one (the same
        device, ``seed``): READ_ACTIVE, GET_STATUS and a STAGE_BEGIN (the next nonce: counter and epoch recovered
        alike) give the same bytes, and the two images after it are the same. Returns the active generation."""
        identity = banks.seeded_identity(seed)
        py_image, c_image = self.py.store.flash.image.copy(), self.c.flash.image.copy()
        c_boot = CFirmware(
            banks.RamFlash(py_image), banks.seeded_identity(seed), LIMITS, with_estimator=False, library=LIBRARY
        )
        py_boot = Firmware(banks.boot(banks.RamFlash(c_image), LIMITS, identity))
        for command in (m.ReadActive(tag=1), m.GetStatus(tag=2), m.StageBegin(tag=3, length=TABLE_BYTES)):
            py_reply, c_reply = m.encode(py_boot.handle(command)), c_boot.handle_bytes(m.encode(command))
            assert c_reply == py_reply, (
                f"cross-boot after {self.steps} steps, {command}:\n py {py_reply}\n  c {c_reply}"
            )
        assert np.array_equal(py_boot.store.flash.image, c_boot.flash.image), f"cross-boot after {self.steps} steps"
        return banks.active_generation(py_boot.store)

    # ------------------------------------------------------------------------------------------------ a step
    def generation(self) -> int:
        return banks.active_generation(self.py.store)

    def upload(self, tag: int) -> None:
        self.command(m.StageBegin(tag=tag, length=TABLE_BYTES))
        for off in range(0, TABLE_BYTES, 16):
            self.command(m.StageChunk(tag=tag, offset=off, data=self.table[off : off + 16]))
        self.command(m.StageVerify(tag=tag, crc32=crc32(self.table)))
        self.command(
            m.Commit(tag=tag, crc32=crc32(self.table), nonce=self.nonce, expected_generation=self.generation())
        )

    def step(self, kind: int, a: int, b: int, c: int) -> None:
        """One command or event, read from four integers (kind 0..16; a < 2**32, b < 2**16, c < 256)."""
        self.steps += 1
        tag = b
        table = self.table
        crc = crc32(table)
        kind %= 17
        if kind == 0:
            self.command(m.GetStatus(tag=tag))
        elif kind == 1:  # an exposure (counter a) or the camera's announcement of its next counter, then a start/stop
            if c < 64:
                self.exposure(a)
            elif c < 128:
                self.py.set_next_frame(a)
                self.c.set_next_frame(a)
            self.command(m.StreamControl(tag=tag, enable=bool(b & 1)))
        elif kind == 2:
            self.table = TABLES[a % len(TABLES)]
            self.command(m.StageBegin(tag=tag, length=TABLE_BYTES if c < 230 else b % 300))
        elif kind == 3:
            self.command(m.StageChunk(tag=tag, offset=0, data=table))
        elif kind == 4:
            offset = b % 100
            self.command(m.StageChunk(tag=tag, offset=offset, data=table[offset : offset + c % 40]))
        elif kind == 5:
            corrupt = bytearray(table[:46])
            corrupt[c % 46] ^= 1 << (a % 8)
            self.command(m.StageChunk(tag=tag, offset=0, data=bytes(corrupt)))
        elif kind == 6:
            self.command(m.StageVerify(tag=tag, crc32=crc if c < 200 else a))
        elif kind == 7:
            self.command(m.ReadStaged(tag=tag))
        elif kind == 8:
            nonce = self.nonce if c < 200 else a
            expected = self.generation() if c % 3 else a % 4
            self.command(m.Commit(tag=tag, crc32=crc if c < 220 else a, nonce=nonce, expected_generation=expected))
        elif kind == 9:
            self.command(m.ReadActive(tag=tag))
        elif kind == 10:
            self.command(m.ReadEstimate(tag=tag))
        elif kind == 11:
            options = _not_commands(tag, a)
            self.command(options[c % len(options)])
        elif kind == 12:
            self.reboot()
        elif kind == 13:
            message = m.StageBegin(tag=tag, length=TABLE_BYTES)
            if c & 1:
                message = m.Commit(tag=tag, crc32=crc, nonce=self.nonce, expected_generation=self.generation())
            self.power_cut(a % (banks.SECTOR_BYTES + 300), message)
        elif kind == 14:
            self.upload(tag)
        elif kind == 15:  # a table with one field at an edge of the rules, or random bits
            value = (
                SPECIAL_VALUES[c % len(SPECIAL_VALUES)] if c < 200 else struct.unpack("<f", a.to_bytes(4, "little"))[0]
            )
            self.table = with_field(TABLES[a % 4], b % N_FIELDS, value)
            self.upload(tag)
        else:  # raw bytes: a message cut short or with a byte changed (the decoders' verdict first)
            raw = bytearray(m.encode(m.Commit(tag=tag, crc32=crc, nonce=self.nonce, expected_generation=a % 3)))
            if c & 1:
                raw[c % len(raw)] ^= (a & 0xFF) or 1
            self.send(bytes(raw[: len(raw) - (c % 3)]))
        self.check_flash()


def aged_image(seed: int, sessions: int) -> np.ndarray:
    """A flash image (written by the Python firmware) after ``sessions`` STAGE_BEGINs: near or past a session-area
    rewrite (STAGE_SLOTS = 248)."""
    store = banks.factory_store(NOMINAL, banks.RamFlash(), LIMITS, banks.seeded_identity(seed))
    for _ in range(sessions):
        banks.stage_begin(store, TABLE_BYTES)
    return store.flash.image.copy()
