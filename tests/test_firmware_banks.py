"""Parameter banks: staging never touches the A/B slots, commit switches atomically with a generation and CRC, and a
power loss or an interrupted upload at any point leaves a valid set active."""

import dataclasses
import math

import numpy as np
import pytest

from hostlink.sky.simulate import seed004_camera
from onboard import banks
from onboard.params import CameraParams, Distortion
from protocol.crc import crc32
from protocol.messages import NakCode, StageState
from protocol.param_table import TABLE_BYTES

CAMERA = seed004_camera()
NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)


def stage(store, params_or_table, chunk=16):
    table = params_or_table if isinstance(params_or_table, bytes) else banks.params_to_table(params_or_table)
    assert banks.stage_begin(store, TABLE_BYTES) is None
    for off in range(0, TABLE_BYTES, chunk):
        assert banks.stage_chunk(store, off, table[off : off + chunk]) is None
    return table, crc32(table)


def upload(store, params):
    table, crc = stage(store, params)
    assert banks.stage_verify(store, crc) is None
    return banks.commit(store, crc)


def test_factory_store_boots_generation_one_in_slot_a():
    store = banks.factory_store(NOMINAL)
    gen, table, crc = banks.active_set(store)
    assert (store.active, gen) == (0, 1)
    assert table == banks.params_to_table(NOMINAL) and crc == crc32(table)


def test_table_round_trip_gives_the_float32_values():
    back = banks.table_to_params(banks.params_to_table(CAMERA))
    assert back.focal_length_mm == float(np.float32(CAMERA.focal_length_mm))
    assert back.distortion.k1 == float(np.float32(CAMERA.distortion.k1))
    assert back.image_size_px == (1024, 1024)


def test_commits_alternate_slots_and_count_generations():
    store = banks.factory_store(NOMINAL)
    assert upload(store, CAMERA) == 2 and store.active == 1
    assert upload(store, NOMINAL) == 3 and store.active == 0
    assert banks.active_set(store)[1] == banks.params_to_table(NOMINAL)
    assert banks.boot(store.slots).active == 0  # a reboot finds the same active set


def test_staging_changes_no_slot_until_commit():
    store = banks.factory_store(NOMINAL)
    before = store.slots.copy()
    table, crc = stage(store, CAMERA)
    assert banks.stage_verify(store, crc) is None
    assert np.array_equal(store.slots, before)
    assert banks.boot(store.slots).active == 0  # host killed here: a reboot keeps the old set


@pytest.mark.parametrize("n_bytes", range(0, banks.RECORD_BYTES))
def test_power_loss_while_programming_keeps_the_old_set(n_bytes):
    store = banks.factory_store(NOMINAL)
    upload(store, CAMERA)  # generation 2 in slot B; slot A (generation 1) is the inactive one now
    record = banks.make_record(3, banks.params_to_table(NOMINAL))
    banks.program_slot(store, 0, record, n_bytes=n_bytes)  # power lost after n_bytes of the next commit
    rebooted = banks.boot(store.slots)
    gen, table, _ = banks.active_set(rebooted)
    assert (rebooted.active, gen, table) == (1, 2, banks.params_to_table(CAMERA))


def test_power_loss_after_programming_boots_the_new_set():
    store = banks.factory_store(NOMINAL)
    banks.program_slot(store, 1, banks.make_record(2, banks.params_to_table(CAMERA)))
    rebooted = banks.boot(store.slots)
    assert rebooted.active == 1 and banks.active_set(rebooted)[0] == 2


def test_commit_needs_a_verified_set_with_the_same_crc():
    store = banks.factory_store(NOMINAL)
    table, crc = stage(store, CAMERA)
    assert banks.commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.stage_verify(store, crc) is None
    assert banks.commit(store, crc ^ 1).code == NakCode.NOT_VERIFIED
    assert banks.stage_chunk(store, 0, table[:4]) is None  # any chunk after verify un-verifies
    assert store.stage_state == StageState.RECEIVING
    assert banks.commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.active_set(store)[0] == 1


def test_a_corrupt_chunk_fails_the_crc_and_commits_nothing():
    store = banks.factory_store(NOMINAL)
    table = bytearray(banks.params_to_table(CAMERA))
    crc = crc32(bytes(table))
    table[5] ^= 0x10  # one bit flipped in transit
    stage(store, bytes(table))
    refusal = banks.stage_verify(store, crc)
    assert refusal.code == NakCode.BAD_CRC and "CRC" in refusal.text
    assert banks.commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.active_set(store)[0] == 1


def test_incomplete_and_out_of_bounds_staging_is_refused():
    store = banks.factory_store(NOMINAL)
    assert banks.stage_chunk(store, 0, b"x").code == NakCode.NOT_STAGED
    assert banks.stage_begin(store, TABLE_BYTES - 1).code == NakCode.BAD_LENGTH
    assert banks.stage_begin(store, TABLE_BYTES) is None
    assert banks.stage_chunk(store, TABLE_BYTES - 2, b"abc").code == NakCode.BAD_LENGTH
    assert banks.stage_chunk(store, 0, bytes(16)) is None
    refusal = banks.stage_verify(store, 0)
    assert refusal.code == NakCode.NOT_STAGED and f"{TABLE_BYTES - 16} of {TABLE_BYTES}" in refusal.text


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"focal_length_mm": math.nan}, "focal_length_mm"),
        ({"focal_length_mm": -70.0}, "focal_length_mm"),
        ({"principal_point_px": (5000.0, 511.5)}, "principal_point_px[0]"),
        ({"distortion": Distortion(k1=1e-5)}, "distortion"),
    ],
    ids=["nan", "negative-focal", "off-detector", "non-monotonic"],
)
def test_invalid_sets_are_refused_with_the_field_and_reason(change, field):
    store = banks.factory_store(NOMINAL)
    bad = dataclasses.replace(CAMERA, **change)
    table, crc = stage(store, bad)
    refusal = banks.stage_verify(store, crc)
    assert refusal.code == NakCode.INVALID_PARAMS
    assert refusal.text.startswith(field + ":")
    assert banks.active_set(store)[0] == 1


def test_fractional_image_size_is_refused():
    from protocol.param_table import encode_table

    values = list(np.frombuffer(banks.params_to_table(CAMERA), "<f4"))
    values[4] = 1023.5
    store = banks.factory_store(NOMINAL)
    table, crc = stage(store, encode_table(values))
    refusal = banks.stage_verify(store, crc)
    assert refusal.code == NakCode.INVALID_PARAMS and refusal.text.startswith("image_size_px[0]")


def test_erased_flash_has_no_active_set():
    store = banks.erased_store()
    assert store.active == banks.NO_SLOT and banks.active_set(store) is None
    assert upload(store, CAMERA) == 1 and store.active == 0


def test_a_commit_past_the_last_generation_is_refused_and_keeps_the_active_set():
    # generations are uint32 in the slot record: the commit after 2**32 - 1 used to raise struct.error out of
    # Firmware.handle (which must answer every command) instead of a NAK
    store = banks.factory_store(NOMINAL)
    store.slots[0] = banks.make_record(2**32 - 1, banks.params_to_table(NOMINAL))
    store = banks.boot(store.slots)
    before = store.slots.copy()
    _, crc = stage(store, CAMERA)
    assert banks.stage_verify(store, crc) is None
    refusal = banks.commit(store, crc)
    assert isinstance(refusal, banks.Refusal) and refusal.code == NakCode.BANK_WRITE_FAILED
    assert np.array_equal(store.slots, before) and banks.active_set(store)[0] == 2**32 - 1
