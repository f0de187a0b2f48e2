"""Parameter banks of the sensor: a staging area and two non-volatile slots (A/B), switched atomically.

Each slot holds one record (``RECORD_BYTES`` = 100 bytes, little-endian)::

    generation:u32 | table: 92 bytes (protocol.param_table: camera fields + 1-sigma prior) | crc32:u32 over both

A blank (erased) slot is all 0xFF and never has a valid CRC. At start-up :func:`boot` makes the valid slot with the
highest generation active. A commit (safe upload step 5) programs the *inactive* slot with the next generation,
reads it back and checks its CRC, and only then switches ``active`` (one integer store: the atomic switch). A power
loss anywhere before the switch leaves the old slot active, since the half-written slot fails its CRC at boot; a
power loss after it boots into the new slot, whose generation is higher. Staging lives in RAM and never touches
the slots, so an interrupted upload (host killed, corrupt chunk, refused set) leaves the active set unchanged.

The checks a staged set must pass (step 3) are exactly :func:`onboard.params.validate_params` and
:func:`onboard.prior.validate_sigma`, so host and sensor refuse a set for the same reason. Buffers are sized at
start-up; every step does a bounded amount of work.
Generations are uint32 and do not wrap: a commit past :data:`MAX_GENERATION` (4e9 commits) is refused.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from onboard.params import CameraParams, Distortion, ParameterError, validate_params
from onboard.prior import unknown_sigma, validate_sigma
from protocol.crc import crc32
from protocol.messages import NakCode, StageState
from protocol.param_table import CAMERA_FIELDS, SIGMA_FIELDS, SIGMA_OFFSET, TABLE_BYTES, decode_table, encode_table

_GEN = struct.Struct("<I")
_CRC = struct.Struct("<I")
RECORD_BYTES = _GEN.size + TABLE_BYTES + _CRC.size
ERASED_BYTE = 0xFF
NO_SLOT = -1
#: Largest generation a slot record holds (uint32); a commit past it is refused (4e9 commits: never in practice).
MAX_GENERATION = (1 << (8 * _GEN.size)) - 1


@dataclass(frozen=True)
class Refusal:
    """Why a bank operation was refused: a protocol NAK code and a one-line reason."""

    code: NakCode
    text: str


@dataclass
class BankStore:
    """The sensor's parameter memory. ``slots`` models the two flash slots; the rest is RAM."""

    slots: np.ndarray  # (2, RECORD_BYTES) uint8
    active: int  # index of the active slot, NO_SLOT before the first commit
    staged: np.ndarray  # (TABLE_BYTES,) uint8
    received: np.ndarray  # (TABLE_BYTES,) bool: which staged bytes arrived since stage_begin
    stage_state: StageState
    verified_crc: int  # CRC of the staged set that passed stage_verify (valid only in state VERIFIED)


# ----------------------------------------------------------------------------------------------- table <-> params
def params_to_table(params: CameraParams, sigma: np.ndarray | None = None) -> bytes:
    """Camera parameter set and its 1-sigma prior (10 values, ESTIMATE_NAMES order, parameter units; NaN or 0 =
    unknown; None = nothing known) -> the table bytes (each value rounded to float32)."""
    values = {
        "focal_length_mm": params.focal_length_mm,
        "pixel_pitch_um": params.pixel_pitch_um,
        "principal_point_x_px": params.principal_point_px[0],
        "principal_point_y_px": params.principal_point_px[1],
        "image_width_px": params.image_size_px[0],
        "image_height_px": params.image_size_px[1],
        **{k: getattr(params.distortion, k) for k in ("k1", "k2", "k3", "p1", "p2", "s1", "s2")},
    }
    sig = unknown_sigma() if sigma is None else np.asarray(sigma, dtype=np.float64).reshape(len(SIGMA_FIELDS))
    return encode_table([float(values[name]) for name in CAMERA_FIELDS] + [float(v) for v in sig])


def table_to_sigma(table: bytes) -> np.ndarray:
    """Table bytes -> the set's 1-sigma prior (10 float32 values, ESTIMATE_NAMES order, NaN/0 = unknown)."""
    return decode_table(table)[SIGMA_OFFSET:]


def table_to_params(table: bytes) -> CameraParams:
    """Table bytes -> camera parameter set (values are the exact float32 ones), NOT validated.
    Raises ParameterError if the image size is not a whole number (it cannot be represented otherwise)."""
    v = [float(x) for x in decode_table(table)]
    for i, n in enumerate(v[4:6]):
        if not (np.isfinite(n) and n == int(n)):
            raise ParameterError(f"image_size_px[{i}]", f"expected a whole number of pixels, got {n!r}")
    return CameraParams(
        focal_length_mm=v[0],
        pixel_pitch_um=v[1],
        principal_point_px=(v[2], v[3]),
        image_size_px=(int(v[4]), int(v[5])),
        distortion=Distortion(*v[6:13]),
    )


def check_table(table: bytes) -> Refusal | None:
    """Sensor-side range checks of a staged set (safe upload step 3): None if usable."""
    try:
        with np.errstate(all="ignore"):  # an absurd value must produce a refusal, not a warning
            validate_params(table_to_params(table))
            validate_sigma(table_to_sigma(table))
    except ParameterError as exc:
        return Refusal(NakCode.INVALID_PARAMS, str(exc))
    return None


# ---------------------------------------------------------------------------------------------------- records
def make_record(generation: int, table: bytes) -> np.ndarray:
    """The slot record (RECORD_BYTES) for ``table`` with ``generation`` (uint8 array)."""
    body = _GEN.pack(generation) + bytes(table)
    return np.frombuffer(body + _CRC.pack(crc32(body)), dtype=np.uint8).copy()


def parse_record(record: np.ndarray) -> tuple[int, bytes] | None:
    """(generation, table) of a slot record, or None if its CRC fails (erased or half-written)."""
    raw = record.tobytes()
    body = raw[: _GEN.size + TABLE_BYTES]
    if crc32(body) != _CRC.unpack_from(raw, len(body))[0]:
        return None
    return _GEN.unpack_from(raw)[0], body[_GEN.size :]


def program_slot(store: BankStore, slot: int, record: np.ndarray, n_bytes: int = RECORD_BYTES) -> None:
    """Write the first ``n_bytes`` of ``record`` into ``slot`` after erasing it (n_bytes < RECORD_BYTES models a
    power loss during programming)."""
    store.slots[slot, :] = ERASED_BYTE
    store.slots[slot, :n_bytes] = record[:n_bytes]


# ------------------------------------------------------------------------------------------------------- state
def erased_store() -> BankStore:
    """A sensor with blank flash and nothing staged."""
    return boot(np.full((2, RECORD_BYTES), ERASED_BYTE, dtype=np.uint8))


def boot(slots: np.ndarray) -> BankStore:
    """Start-up: the valid slot with the highest generation becomes active (NO_SLOT if neither is valid)."""
    slots = np.asarray(slots, dtype=np.uint8).reshape(2, RECORD_BYTES).copy()
    best, best_gen = NO_SLOT, -1
    for slot in range(2):
        parsed = parse_record(slots[slot])
        if parsed is not None and parsed[0] > best_gen:
            best, best_gen = slot, parsed[0]
    return BankStore(
        slots=slots,
        active=best,
        staged=np.zeros(TABLE_BYTES, dtype=np.uint8),
        received=np.zeros(TABLE_BYTES, dtype=bool),
        stage_state=StageState.EMPTY,
        verified_crc=0,
    )


def active_set(store: BankStore) -> tuple[int, bytes, int] | None:
    """(generation, table, crc32) of the active set, or None before the first commit."""
    if store.active == NO_SLOT:
        return None
    parsed = parse_record(store.slots[store.active])
    if parsed is None:  # cannot happen: a slot only becomes active after its CRC was checked
        return None
    generation, table = parsed
    return generation, table, crc32(table)


def stage_begin(store: BankStore, length: int) -> Refusal | None:
    """Safe upload step 2a: clear the staging area (RAM only)."""
    if length != TABLE_BYTES:
        return Refusal(NakCode.BAD_LENGTH, f"a parameter table is {TABLE_BYTES} bytes, not {length}")
    store.staged[:] = 0
    store.received[:] = False
    store.stage_state = StageState.RECEIVING
    store.verified_crc = 0
    return None


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
    """Safe upload step 3: the staged bytes must be complete, match ``crc`` and pass the range checks."""
    if not staged_complete(store):
        missing = int(np.count_nonzero(~store.received)) if store.stage_state != StageState.EMPTY else TABLE_BYTES
        return Refusal(NakCode.NOT_STAGED, f"staged set incomplete ({missing} of {TABLE_BYTES} bytes missing)")
    table = store.staged.tobytes()
    actual = crc32(table)
    if actual != crc:
        store.stage_state = StageState.RECEIVING
        return Refusal(NakCode.BAD_CRC, f"staged set has CRC 0x{actual:08x}, host sent 0x{crc:08x}")
    refusal = check_table(table)
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


def commit(store: BankStore, crc: int) -> int | Refusal:
    """Safe upload step 5: program the inactive slot with the verified set and the next generation, check it,
    switch. Returns the new generation, or a Refusal with the active set unchanged."""
    if store.stage_state != StageState.VERIFIED:
        return Refusal(NakCode.NOT_VERIFIED, "the staged set has not passed STAGE_VERIFY")
    table = store.staged.tobytes()
    if crc != store.verified_crc or crc32(table) != crc:
        return Refusal(
            NakCode.NOT_VERIFIED, f"CRC 0x{crc:08x} is not that of the verified staged set 0x{store.verified_crc:08x}"
        )
    current = active_set(store)
    generation = 1 if current is None else current[0] + 1
    if generation > MAX_GENERATION:
        return Refusal(NakCode.BANK_WRITE_FAILED, f"generation counter exhausted at {MAX_GENERATION}; nothing switched")
    slot = 0 if store.active == NO_SLOT else 1 - store.active
    record = make_record(generation, table)
    program_slot(store, slot, record)
    if parse_record(store.slots[slot]) != (generation, table):
        return Refusal(NakCode.BANK_WRITE_FAILED, f"slot {'AB'[slot]} did not read back intact; nothing switched")
    store.active = slot  # the atomic switch
    store.stage_state = StageState.EMPTY
    store.received[:] = False
    store.verified_crc = 0
    return generation


def factory_store(params: CameraParams) -> BankStore:
    """A sensor as delivered: blank flash with ``params`` committed as generation 1 in slot A (validated)."""
    validate_params(params)
    store = erased_store()
    program_slot(store, 0, make_record(1, params_to_table(params)))
    return boot(store.slots)
