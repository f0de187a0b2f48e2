"""Parameter banks of the sensor: a RAM staging area and two NOR-flash sectors (A/B), switched atomically, with a
persisted staging-session counter that binds every commit to the session that staged it.

Flash model (:class:`RamFlash`; the emulator's file-backed image, ``hostlink.emulator.flash``, applies the same
rules through :func:`nor_erase` / :func:`nor_program`): ``N_SECTORS`` = 2 sectors of ``SECTOR_BYTES`` = 4096 bytes
(a common NOR sector). Erasing sets a sector to 0xFF; programming can only clear bits (``new = old & data``), in
aligned units of ``WRITE_BYTES`` = 8 bytes (a double word, as on Cortex-M internal flash). A power cut may stop an
erase or a program after any byte.

Records (little-endian, each a whole number of write units, each closed by a CRC-32 over the bytes before it)::

    bank record  (BANK_RECORD_BYTES = 120, at offset 0 of a sector)
        magic "BNK2":u32 | seq:u32 | generation:u32 | nonce_counter:u32 | epoch:u32 | reserved 0xFFFFFFFF |
        table: 92 bytes | crc32:u32
    stage record (STAGE_RECORD_BYTES = 16, appended after the bank record of the active sector)
        magic "STG2":u32 | epoch:u32 | counter:u32 | crc32:u32 over the 12 bytes before

A record whose CRC fails (erased, half-written, half-erased) does not exist. At start-up :func:`boot` makes the
valid bank record with the highest ``seq`` active, and sets the session counter to the largest value any valid
record holds (and the flash epoch to that record's). A commit (safe upload step 5) erases the *inactive* sector,
programs a bank record there with ``seq + 1``, the next generation and the current counter and epoch, reads it back,
and only then switches ``active`` (one integer store: the atomic switch). A power cut before the record's last byte
leaves it without a valid CRC, so the old sector stays active; after it, the new record wins by its ``seq``. Either
way the active set is the complete old or the complete new one. Staging lives in RAM, so an interrupted upload
leaves the active set unchanged.

Session binding (issues 15 and 33): STAGE_BEGIN takes the next counter value, persists it (a stage record,
programmed and read back before anything is answered), and answers with the session's nonce, :func:`session_nonce`
of the device's identity, the flash epoch and that counter. COMMIT must carry that nonce and the generation it
expects to replace. The nonce is bound to

* the moment: the counter is persisted before a nonce is given out and only grows, and for one device and epoch the
  nonce is a bijection of the counter (a 4-round Feistel permutation of 32 bits), so a nonce is never issued twice,
  across power cycles too;
* the device: the permutation is keyed by the device's unique identity (:class:`DeviceIdentity`: the MCU's 96-bit
  unique ID, read-only, and a random source, both behind the platform's HAL) and by
* the flash's life: the epoch, a 32-bit value drawn from the random source when the flash holds no record at all (a
  new unit, a wiped flash) and carried by every record from then on.

Recorded traffic (whole, in part, reordered) therefore carries an old nonce or an old generation on the sensor that
produced it, and a nonce of another key on any other sensor or on the same sensor after its flash was wiped: it
commits nothing (but for a 2**-32 chance per replayed session that the two keys' permutations agree on it; no clock
is involved). When the active sector has no room for another stage record, STAGE_BEGIN first rewrites the active
set (same generation and table, ``seq + 1``) into the other sector, which then has room again: STAGE_SLOTS = 248
sessions per rewrite.

The checks a staged set must pass (step 3) are :func:`onboard.params.check_plausible` with the sensor's declared
:class:`~onboard.params.PlausibilityLimits`, and :func:`onboard.prior.validate_sigma`, so host and sensor refuse a
set for the same reason. Buffers are sized at start-up; every step does a bounded amount of work.
Generations, seqs and nonces are uint32 and do not wrap: past :data:`MAX_COUNTER` (4e9) a commit or session is
refused. The C translation is ``onboard/c/banks.c`` (the platform's flash and identity behind ``banks_hal_t``),
held to the same replies and flash bytes (docs/port-kit.md, section 6).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from onboard.params import (
    CameraParams,
    ParameterError,
    PlausibilityLimits,
    check_plausible,
    params_from_dict,
    params_to_dict,
)
from onboard.prior import unknown_sigma, validate_sigma
from protocol.crc import crc32
from protocol.messages import NakCode, StageState
from protocol.param_table import (
    SIGMA_FIELDS,
    SIGMA_OFFSET,
    TABLE_BYTES,
    camera_fields_from_file,
    camera_file_from_fields,
    decode_table,
    table_from_mapping,
    table_to_mapping,
)

#: Precision of the sensor's checks (float32, as the rest of the sensor; the host runs them in float64: the verdicts
#: agree except within a few float32 ulps of a bound, tests/test_params_plausibility.py).
SENSOR_DTYPE = np.float32
#: NOR geometry: sectors, bytes per sector, program granularity [bytes].
N_SECTORS = 2
SECTOR_BYTES = 4096
WRITE_BYTES = 8
FLASH_BYTES = N_SECTORS * SECTOR_BYTES
ERASED_BYTE = 0xFF
NO_SLOT = -1
#: Largest generation / seq / nonce (uint32); nothing wraps.
MAX_COUNTER = (1 << 32) - 1
MAX_GENERATION = MAX_COUNTER

_BANK_MAGIC = 0x324B4E42  # "BNK2"
_STAGE_MAGIC = 0x32475453  # "STG2"
_BANK_HEAD = struct.Struct("<IIIIII")  # magic, seq, generation, nonce_counter, epoch, reserved
_RESERVED = 0xFFFFFFFF
_STAGE_HEAD = struct.Struct("<III")  # magic, epoch, counter
_CRC = struct.Struct("<I")
BANK_RECORD_BYTES = _BANK_HEAD.size + TABLE_BYTES + _CRC.size
STAGE_RECORD_BYTES = 16
#: Stage records that fit after the bank record of a sector.
STAGE_SLOTS = (SECTOR_BYTES - BANK_RECORD_BYTES) // STAGE_RECORD_BYTES
assert BANK_RECORD_BYTES % WRITE_BYTES == 0 and STAGE_RECORD_BYTES % WRITE_BYTES == 0


# --------------------------------------------------------------------------------------------------- NOR flash
class PowerCut(Exception):  # noqa: N818 - an event, not an error of the caller
    """The modelled power failed during an erase or program: the operation stopped part-way."""


def nor_erase(image: np.ndarray, sector: int, budget: int | None = None) -> int:
    """Erase ``sector`` of ``image`` (uint8) to 0xFF, byte by byte in address order. ``budget``: bytes that can still
    be changed before the power fails (None = no cut). Returns the bytes done; stops short when the budget runs out."""
    start = sector * SECTOR_BYTES
    n = SECTOR_BYTES if budget is None else max(0, min(SECTOR_BYTES, budget))
    image[start : start + n] = ERASED_BYTE
    return n


def nor_program(image: np.ndarray, address: int, data: np.ndarray, budget: int | None = None) -> int:
    """Program ``data`` at ``address``: bits can only be cleared (``old & data``); address and length are whole
    write units (a programming error otherwise). ``budget`` as :func:`nor_erase`. Returns the bytes done."""
    data = np.asarray(data, dtype=np.uint8)
    if address % WRITE_BYTES or len(data) % WRITE_BYTES or address < 0 or address + len(data) > len(image):
        raise ValueError(f"program of {len(data)} bytes at {address}: not whole {WRITE_BYTES}-byte units in flash")
    n = len(data) if budget is None else max(0, min(len(data), budget))
    image[address : address + n] &= data[:n]
    return n


class RamFlash:
    """NOR flash held in memory (the sensor model's default). ``power_budget``: bytes that may still be erased or
    programmed before a :class:`PowerCut` (None = power never fails), the in-process power-cut test's hook."""

    def __init__(self, image: np.ndarray | None = None, power_budget: int | None = None) -> None:
        self.image = (
            np.full(FLASH_BYTES, ERASED_BYTE, dtype=np.uint8)
            if image is None
            else np.array(image, dtype=np.uint8).reshape(FLASH_BYTES)
        )
        self.power_budget = power_budget

    def read(self, address: int, n: int) -> bytes:
        return self.image[address : address + n].tobytes()

    def _spend(self, done: int, wanted: int) -> None:
        if self.power_budget is not None:
            self.power_budget -= done
            if done < wanted:
                raise PowerCut(f"power cut after {done} of {wanted} bytes")

    def erase(self, sector: int) -> None:
        self._spend(nor_erase(self.image, sector, self.power_budget), SECTOR_BYTES)

    def program(self, address: int, data: bytes) -> None:
        arr = np.frombuffer(bytes(data), dtype=np.uint8)
        self._spend(nor_program(self.image, address, arr, self.power_budget), len(arr))


class FlashDevice(Protocol):
    """What the banks need from a flash device (:class:`RamFlash`, ``hostlink.emulator.flash.FileFlash``): the NOR
    rules of :func:`nor_erase` and :func:`nor_program`."""

    def read(self, address: int, n: int) -> bytes:
        """``n`` bytes from ``address``."""

    def erase(self, sector: int) -> None:
        """Erase ``sector`` to 0xFF."""

    def program(self, address: int, data: bytes) -> None:
        """Program whole write units at ``address`` (bits only cleared)."""


# ----------------------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class BankRecord:
    seq: int
    generation: int
    nonce_counter: int
    table: bytes
    epoch: int = 0  # the flash epoch the record carries (module docstring)


def encode_bank_record(record: BankRecord) -> bytes:
    """The BANK_RECORD_BYTES of a bank record (module docstring)."""
    head = _BANK_HEAD.pack(_BANK_MAGIC, record.seq, record.generation, record.nonce_counter, record.epoch, _RESERVED)
    body = head + bytes(record.table)
    return body + _CRC.pack(crc32(body))


def decode_bank_record(raw: bytes) -> BankRecord | None:
    """A bank record from its bytes, or None if it is not one (erased, half-written: magic or CRC wrong)."""
    raw = bytes(raw[:BANK_RECORD_BYTES])
    if len(raw) != BANK_RECORD_BYTES:
        return None
    body = raw[: -_CRC.size]
    magic, seq, generation, counter, epoch, _ = _BANK_HEAD.unpack_from(body)
    if magic != _BANK_MAGIC or crc32(body) != _CRC.unpack_from(raw, len(body))[0]:
        return None
    return BankRecord(seq, generation, counter, body[_BANK_HEAD.size :], epoch)


def encode_stage_record(counter: int, epoch: int) -> bytes:
    """The STAGE_RECORD_BYTES of a stage record holding a session's ``counter`` and the flash ``epoch``."""
    body = _STAGE_HEAD.pack(_STAGE_MAGIC, epoch, counter)
    return body + _CRC.pack(crc32(body))


def decode_stage_record(raw: bytes) -> tuple[int, int] | None:
    """(counter, epoch) of a stage record, or None if it is not one."""
    raw = bytes(raw[:STAGE_RECORD_BYTES])
    if len(raw) != STAGE_RECORD_BYTES:
        return None
    body = raw[: _STAGE_HEAD.size]
    magic, epoch, counter = _STAGE_HEAD.unpack_from(body)
    if magic != _STAGE_MAGIC or crc32(body) != _CRC.unpack_from(raw, len(body))[0]:
        return None
    return counter, epoch


# ------------------------------------------------------------------------------------------------ session nonces
#: Bytes of the device's unique identity (a 96-bit MCU unique ID, as STM32 and most Cortex-M parts carry).
UID_BYTES = 12
#: Feistel rounds of the nonce permutation and the odd multiplier of its round function (2**32 / golden ratio).
_NONCE_ROUNDS = 4
_ROUND_MULTIPLIER = 0x9E3779B1


def nonce_keys(uid: bytes, epoch: int) -> tuple[int, ...]:
    """The nonce permutation's round keys: CRC-32 of the identity, the epoch (u32 LE) and the round number (u8)."""
    base = bytes(uid) + struct.pack("<I", epoch)
    return tuple(crc32(base + bytes([i])) for i in range(_NONCE_ROUNDS))


def session_nonce(uid: bytes, epoch: int, counter: int) -> int:
    """The staging session's nonce: a 4-round Feistel permutation of the 32-bit ``counter`` (halves of 16 bits,
    round function ((R ^ K) * 0x9E3779B1 mod 2**32) >> 16) keyed by :func:`nonce_keys`. A bijection of the counter
    for one key: a device never issues a nonce twice; another key (device, epoch) maps a counter elsewhere."""
    left, right = counter >> 16 & 0xFFFF, counter & 0xFFFF
    for key in nonce_keys(uid, epoch):
        left, right = right, left ^ ((((right ^ key) * _ROUND_MULTIPLIER) & 0xFFFFFFFF) >> 16)
    return left << 16 | right


class SeededRandom:
    """A deterministic 32-bit random source (xorshift32 of a nonzero seed): the model of a TRNG where a test needs the
    same draws in two firmwares. A real sensor draws from its hardware random generator."""

    def __init__(self, seed: int) -> None:
        self.state = (seed & 0xFFFFFFFF) or 0x6D2B79F5

    def __call__(self) -> int:
        x = self.state
        x ^= (x << 13) & 0xFFFFFFFF
        x ^= x >> 17
        x ^= (x << 5) & 0xFFFFFFFF
        self.state = x
        return x


class _GeneratorRandom:
    """32-bit draws from a numpy Generator seeded from the operating system's entropy."""

    def __init__(self) -> None:
        self.rng = np.random.default_rng()

    def __call__(self) -> int:
        return int(self.rng.integers(0, 1 << 32, dtype=np.uint64))


@dataclass(frozen=True)
class DeviceIdentity:
    """What the platform gives the banks to bind a session to the device: its unique ID (UID_BYTES) and a random
    source (a callable returning a uint32; drawn only for a new epoch)."""

    uid: bytes
    random32: Callable[[], int]


def seeded_identity(seed: int) -> DeviceIdentity:
    """A reproducible device (tests, the C port's equivalence runs): uid and random source from ``seed``."""
    gen = SeededRandom(seed * 2654435761 + 1)
    return DeviceIdentity(b"".join(struct.pack("<I", gen()) for _ in range(UID_BYTES // 4)), SeededRandom(seed + 7))


def random_identity() -> DeviceIdentity:
    """A new device: uid and random source from the operating system's entropy (the model's default)."""
    gen = _GeneratorRandom()
    return DeviceIdentity(b"".join(struct.pack("<I", gen()) for _ in range(UID_BYTES // 4)), gen)


def _stage_slot_address(sector: int, k: int) -> int:
    return sector * SECTOR_BYTES + BANK_RECORD_BYTES + k * STAGE_RECORD_BYTES


# ----------------------------------------------------------------------------------------------------- the store
@dataclass(frozen=True)
class Refusal:
    """Why a bank operation was refused: a protocol NAK code and a one-line reason."""

    code: NakCode
    text: str


@dataclass
class BankStore:
    """The sensor's parameter memory: the flash device, what boot found in it, and the RAM staging area."""

    flash: FlashDevice
    active: int  # sector of the active bank record, NO_SLOT before the first commit
    active_record: BankRecord | None
    nonce_counter: int  # largest nonce ever persisted (0: none)
    stage_free: int  # next free stage slot in the stage sector (STAGE_SLOTS: full)
    staged: np.ndarray  # (TABLE_BYTES,) uint8
    received: np.ndarray  # (TABLE_BYTES,) bool: which staged bytes arrived since stage_begin
    stage_state: StageState
    verified_crc: int  # CRC of the staged set that passed stage_verify (valid only in state VERIFIED)
    stage_nonce: int  # nonce of the current staging session (0: none)
    limits: PlausibilityLimits | None  # the sensor's declared design (None: no focal-length rule)
    identity: DeviceIdentity = field(default_factory=random_identity)  # the device's uid and random source
    epoch: int = 0  # the flash epoch (0: the flash holds no record yet; drawn at the first write)


def _stage_sector(active: int) -> int:
    """Stage records live in the sector the next commit does not erase: the active one (sector 1 while none is)."""
    return 1 if active == NO_SLOT else active


def boot(
    flash: FlashDevice, limits: PlausibilityLimits | None = None, identity: DeviceIdentity | None = None
) -> BankStore:
    """Start-up: the valid bank record with the highest seq becomes active (NO_SLOT if none); the session counter is
    the largest value any valid record holds, the epoch the first valid record's (sector A's bank record, its stage
    records, then sector B's: every record of one flash carries the same epoch; 0 when there is none); staging is
    empty. ``identity``: the device's (default: :func:`random_identity`, a new device)."""
    best, record = NO_SLOT, None
    counter = 0
    epoch = 0
    for sector in range(N_SECTORS):
        rec = decode_bank_record(flash.read(sector * SECTOR_BYTES, BANK_RECORD_BYTES))
        if rec is not None:
            counter = max(counter, rec.nonce_counter)
            epoch = epoch or rec.epoch
            if record is None or rec.seq > record.seq:
                best, record = sector, rec
        for k in range(STAGE_SLOTS):
            stage = decode_stage_record(flash.read(_stage_slot_address(sector, k), STAGE_RECORD_BYTES))
            if stage is not None:
                counter = max(counter, stage[0])
                epoch = epoch or stage[1]
    return BankStore(
        flash=flash,
        active=best,
        active_record=record,
        nonce_counter=counter,
        stage_free=_first_free_stage_slot(flash, _stage_sector(best)),
        staged=np.zeros(TABLE_BYTES, dtype=np.uint8),
        received=np.zeros(TABLE_BYTES, dtype=bool),
        stage_state=StageState.EMPTY,
        verified_crc=0,
        stage_nonce=0,
        limits=limits,
        identity=random_identity() if identity is None else identity,
        epoch=epoch,
    )


def _first_free_stage_slot(flash: FlashDevice, sector: int) -> int:
    """First stage slot after the last used one (a half-written slot is used: it cannot be programmed again)."""
    free = 0
    for k in range(STAGE_SLOTS):
        if any(b != ERASED_BYTE for b in flash.read(_stage_slot_address(sector, k), STAGE_RECORD_BYTES)):
            free = k + 1
    return free


def erased_store(limits: PlausibilityLimits | None = None, identity: DeviceIdentity | None = None) -> BankStore:
    """A sensor with blank flash and nothing staged."""
    return boot(RamFlash(), limits, identity)


def factory_store(
    params: CameraParams,
    flash: FlashDevice | None = None,
    limits: PlausibilityLimits | None = None,
    identity: DeviceIdentity | None = None,
) -> BankStore:
    """A sensor as delivered: ``flash`` (blank, in RAM by default) with ``params`` committed as generation 1 in
    sector A (validated), under a new epoch drawn from the device's random source. The design the sensor declares is
    ``limits``, by default ``params``' focal length."""
    limits = PlausibilityLimits(params.focal_length_mm) if limits is None else limits
    check_plausible(params, limits)
    identity = random_identity() if identity is None else identity
    flash = RamFlash() if flash is None else flash
    flash.erase(0)
    flash.program(0, encode_bank_record(BankRecord(1, 1, 0, params_to_table(params), draw_epoch(identity))))
    return boot(flash, limits, identity)


def draw_epoch(identity: DeviceIdentity) -> int:
    """A new flash epoch from the device's random source (0 means "none": a draw of 0 becomes 1)."""
    return int(identity.random32()) & 0xFFFFFFFF or 1


def active_set(store: BankStore) -> tuple[int, bytes, int] | None:
    """(generation, table, crc32) of the active set, or None before the first commit."""
    rec = store.active_record
    if rec is None:
        return None
    return rec.generation, rec.table, crc32(rec.table)


def active_generation(store: BankStore) -> int:
    """Generation of the active set (0 before the first commit)."""
    return 0 if store.active_record is None else store.active_record.generation


def _write_bank(store: BankStore, record: BankRecord) -> Refusal | None:
    """Erase the inactive sector, program ``record`` there, read it back, switch. A PowerCut propagates."""
    target = 0 if store.active == NO_SLOT else 1 - store.active
    raw = encode_bank_record(record)
    store.flash.erase(target)
    store.flash.program(target * SECTOR_BYTES, raw)
    if decode_bank_record(store.flash.read(target * SECTOR_BYTES, BANK_RECORD_BYTES)) != record:
        return Refusal(NakCode.BANK_WRITE_FAILED, f"sector {'AB'[target]} did not read back intact; nothing switched")
    store.active, store.active_record = target, record  # the atomic switch
    store.stage_free = 0  # the new active sector was just erased: its stage area is empty
    return None


# ------------------------------------------------------------------------------------------------ table <-> params
def params_to_table(params: CameraParams, sigma: np.ndarray | None = None) -> bytes:
    """Camera parameter set and its 1-sigma prior (10 values, ESTIMATE_NAMES order, parameter units; NaN or 0 =
    unknown; None = nothing known) -> the table bytes (each value rounded to float32)."""
    sig = unknown_sigma() if sigma is None else np.asarray(sigma, dtype=np.float64).reshape(len(SIGMA_FIELDS))
    sigma_fields = {name: float(v) for name, v in zip(SIGMA_FIELDS, sig, strict=True)}
    return table_from_mapping({**camera_fields_from_file(params_to_dict(params)), **sigma_fields})


def table_to_sigma(table: bytes) -> np.ndarray:
    """Table bytes -> the set's 1-sigma prior (10 float32 values, ESTIMATE_NAMES order, NaN/0 = unknown)."""
    return decode_table(table)[SIGMA_OFFSET:]


def table_to_params(table: bytes) -> CameraParams:
    """Table bytes -> camera parameter set (values are the exact float32 ones), NOT validated.
    Raises ParameterError if the image size is not a whole number (it cannot be represented otherwise)."""
    return params_from_dict(camera_file_from_fields(table_to_mapping(table)), validate=False)


def check_table(table: bytes, limits: PlausibilityLimits | None = None) -> Refusal | None:
    """Sensor-side checks of a staged set (safe upload step 3): None if usable, else the rule it breaks."""
    try:
        with np.errstate(all="ignore"):  # an absurd value must produce a refusal, not a warning
            check_plausible(table_to_params(table), limits, SENSOR_DTYPE)
            validate_sigma(table_to_sigma(table))
    except ParameterError as exc:
        return Refusal(NakCode.INVALID_PARAMS, str(exc))
    return None


# ------------------------------------------------------------------------------------------------------ staging
def stage_begin(store: BankStore, length: int) -> int | Refusal:
    """Safe upload step 2a: a new staging session. Persists the next nonce (a stage record, read back) and returns
    it; clears the staging area (RAM). Any earlier session's nonce is void from here on."""
    if length != TABLE_BYTES:
        return Refusal(NakCode.BAD_LENGTH, f"a parameter table is {TABLE_BYTES} bytes, not {length}")
    _clear_staging(store)
    if store.nonce_counter >= MAX_COUNTER:
        return Refusal(NakCode.BANK_WRITE_FAILED, f"staging-session counter exhausted at {MAX_COUNTER}")
    if store.stage_free >= STAGE_SLOTS and store.active_record is not None:
        rec = store.active_record  # no room: rewrite the active set into the other sector (same generation)
        if rec.seq >= MAX_COUNTER:
            return Refusal(NakCode.BANK_WRITE_FAILED, f"bank sequence counter exhausted at {MAX_COUNTER}")
        refusal = _write_bank(store, BankRecord(rec.seq + 1, rec.generation, store.nonce_counter, rec.table, rec.epoch))
        if refusal is not None:
            return refusal
    elif store.stage_free >= STAGE_SLOTS:  # blank flash, stage sector full: start it again
        store.flash.erase(_stage_sector(store.active))
        store.stage_free = 0
    if store.epoch == 0:  # the flash holds no record: a new unit or a wiped flash starts a new epoch
        store.epoch = draw_epoch(store.identity)
    counter = store.nonce_counter + 1
    nonce = session_nonce(store.identity.uid, store.epoch, counter)
    if nonce == 0:  # 0 means "no session": the one counter the permutation maps there is skipped
        counter += 1
        nonce = session_nonce(store.identity.uid, store.epoch, counter)
    if counter > MAX_COUNTER:
        return Refusal(NakCode.BANK_WRITE_FAILED, f"staging-session counter exhausted at {MAX_COUNTER}")
    address = _stage_slot_address(_stage_sector(store.active), store.stage_free)
    store.stage_free += 1  # a half-written slot stays used
    store.flash.program(address, encode_stage_record(counter, store.epoch))
    if decode_stage_record(store.flash.read(address, STAGE_RECORD_BYTES)) != (counter, store.epoch):
        return Refusal(NakCode.BANK_WRITE_FAILED, "the staging-session record did not read back; try again")
    store.nonce_counter = counter
    store.stage_nonce = nonce
    store.stage_state = StageState.RECEIVING
    return nonce


def _clear_staging(store: BankStore) -> None:
    store.staged[:] = 0
    store.received[:] = False
    store.stage_state = StageState.EMPTY
    store.verified_crc = 0
    store.stage_nonce = 0


def stage_chunk(store: BankStore, offset: int, data: bytes) -> Refusal | None:
    """Safe upload step 2b: copy ``data`` to ``offset``. Any chunk after a verify un-verifies the set."""
    if store.stage_state == StageState.EMPTY:
        return Refusal(NakCode.NOT_STAGED, "no upload in progress (send STAGE_BEGIN first)")
    if offset < 0 or len(data) == 0 or offset + len(data) > TABLE_BYTES:
        return Refusal(
            NakCode.BAD_LENGTH, f"chunk of {len(data)} bytes at offset {offset} is outside the {TABLE_BYTES}-byte table"
        )
    store.staged[offset : offset + len(data)] = np.frombuffer(bytes(data), dtype=np.uint8)
    store.received[offset : offset + len(data)] = True
    store.stage_state = StageState.RECEIVING
    store.verified_crc = 0
    return None


def staged_complete(store: BankStore) -> bool:
    return store.stage_state != StageState.EMPTY and bool(np.all(store.received))


def stage_verify(store: BankStore, crc: int) -> Refusal | None:
    """Safe upload step 3: the staged bytes must be complete, match ``crc`` and pass the plausibility checks."""
    if not staged_complete(store):
        missing = int(np.count_nonzero(~store.received)) if store.stage_state != StageState.EMPTY else TABLE_BYTES
        return Refusal(NakCode.NOT_STAGED, f"staged set incomplete ({missing} of {TABLE_BYTES} bytes missing)")
    table = store.staged.tobytes()
    actual = crc32(table)
    if actual != crc:
        store.stage_state = StageState.RECEIVING
        return Refusal(NakCode.BAD_CRC, f"staged set has CRC 0x{actual:08x}, host sent 0x{crc:08x}")
    refusal = check_table(table, store.limits)
    if refusal is not None:
        store.stage_state = StageState.RECEIVING
        return refusal
    store.stage_state = StageState.VERIFIED
    store.verified_crc = actual
    return None


def staged_set(store: BankStore) -> tuple[bytes, int] | None:
    """(table, crc32) of a complete staged set, or None."""
    if not staged_complete(store):
        return None
    table = store.staged.tobytes()
    return table, crc32(table)


def commit(store: BankStore, crc: int, nonce: int, expected_generation: int) -> int | Refusal:
    """Safe upload step 5: program the inactive sector with the verified set and the next generation, check it,
    switch. ``nonce`` must be the current staging session's (STAGE_BEGIN's answer) and ``expected_generation`` the
    active generation (0: none yet). Returns the new generation, or a Refusal with the active set unchanged."""
    current = active_generation(store)
    if store.stage_nonce == 0 or nonce != store.stage_nonce:
        return Refusal(NakCode.STALE_SESSION, f"nonce {nonce} is not the current staging session's; nothing switched")
    if expected_generation != current:
        return Refusal(
            NakCode.STALE_SESSION,
            f"expected generation {expected_generation} but generation {current} is active; nothing switched",
        )
    if store.stage_state != StageState.VERIFIED:
        return Refusal(NakCode.NOT_VERIFIED, "the staged set has not passed STAGE_VERIFY")
    table = store.staged.tobytes()
    if crc != store.verified_crc or crc32(table) != crc:
        return Refusal(
            NakCode.NOT_VERIFIED, f"CRC 0x{crc:08x} is not that of the verified staged set 0x{store.verified_crc:08x}"
        )
    generation = current + 1
    seq = 1 if store.active_record is None else store.active_record.seq + 1
    if generation > MAX_GENERATION or seq > MAX_COUNTER:
        return Refusal(NakCode.BANK_WRITE_FAILED, f"generation counter exhausted at {MAX_GENERATION}; nothing switched")
    refusal = _write_bank(store, BankRecord(seq, generation, store.nonce_counter, table, store.epoch))
    if refusal is not None:
        return refusal
    _clear_staging(store)  # the session is used up: its nonce commits nothing more
    return generation
