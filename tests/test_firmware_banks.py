"""Parameter banks in NOR flash: staging never touches the flash but for its session record, a commit switches
atomically with a generation and CRC, a power cut at any byte of any erase or program leaves the complete old or the
complete new set active, a commit only counts inside its staging session, and an implausible set is refused with the
rule it breaks."""

import copy
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
STALE = NakCode.STALE_SESSION


def stage(store, params_or_table, chunk=16):
    table = params_or_table if isinstance(params_or_table, bytes) else banks.params_to_table(params_or_table)
    nonce = banks.stage_begin(store, TABLE_BYTES)
    assert isinstance(nonce, int) and nonce > 0
    for off in range(0, TABLE_BYTES, chunk):
        assert banks.stage_chunk(store, off, table[off : off + chunk]) is None
    return table, crc32(table)


def commit(store, crc):
    """A COMMIT bound to the current session and the active generation (what a correct host sends)."""
    return banks.commit(store, crc, store.stage_nonce, banks.active_generation(store))


def upload(store, params):
    table, crc = stage(store, params)
    assert banks.stage_verify(store, crc) is None
    return commit(store, crc)


def reboot(store):
    """Power cycle: a fresh boot from a copy of the flash contents (RAM lost)."""
    return banks.boot(banks.RamFlash(store.flash.image.copy()), store.limits, store.identity)


def test_factory_store_boots_generation_one_in_sector_a():
    store = banks.factory_store(NOMINAL)
    gen, table, crc = banks.active_set(store)
    assert (store.active, gen) == (0, 1)
    assert table == banks.params_to_table(NOMINAL) and crc == crc32(table)


def test_table_round_trip_gives_the_float32_values():
    back = banks.table_to_params(banks.params_to_table(CAMERA))
    assert back.focal_length_mm == float(np.float32(CAMERA.focal_length_mm))
    assert back.distortion.k1 == float(np.float32(CAMERA.distortion.k1))
    assert back.image_size_px == (1024, 1024)


def test_commits_alternate_sectors_and_count_generations():
    store = banks.factory_store(NOMINAL)
    assert upload(store, CAMERA) == 2 and store.active == 1
    assert upload(store, NOMINAL) == 3 and store.active == 0
    assert banks.active_set(store)[1] == banks.params_to_table(NOMINAL)
    again = reboot(store)  # a reboot finds the same active set
    assert again.active == 0 and banks.active_set(again) == banks.active_set(store)


def test_staging_writes_only_its_session_record_until_commit():
    store = banks.factory_store(NOMINAL)
    before = store.flash.image.copy()
    table, crc = stage(store, CAMERA)
    assert banks.stage_verify(store, crc) is None
    changed = np.flatnonzero(store.flash.image != before)
    start = banks.BANK_RECORD_BYTES  # the session record, right after sector A's bank record
    assert changed.min() >= start and changed.max() < start + banks.STAGE_RECORD_BYTES
    assert banks.active_set(reboot(store))[0] == 1  # host killed here: a reboot keeps the old set


def test_nor_programming_only_clears_bits_in_whole_write_units():
    image = np.full(banks.FLASH_BYTES, 0xFF, dtype=np.uint8)
    banks.nor_program(image, 0, np.array([0x0F] * 8, dtype=np.uint8))
    banks.nor_program(image, 0, np.array([0xF3] * 8, dtype=np.uint8))
    assert np.all(image[:8] == 0x03) and np.all(image[8:] == 0xFF)  # 0x0F & 0xF3: bits only cleared
    with pytest.raises(ValueError, match="units"):
        banks.nor_program(image, 4, np.zeros(8, dtype=np.uint8))
    banks.nor_erase(image, 0)
    assert np.all(image == 0xFF)


def _store_ready_to_commit(params):
    store = banks.factory_store(NOMINAL)
    assert upload(store, CAMERA) == 2  # sector A (generation 1) is now the inactive one, B holds generation 2
    table, crc = stage(store, params)
    assert banks.stage_verify(store, crc) is None
    return store, crc


def test_a_power_cut_at_every_byte_of_a_commit_leaves_the_complete_old_or_new_set():
    """The commit erases sector A (4096 bytes, byte by byte) then programs the 112-byte record: one cut after each of
    those 4208 bytes, each followed by a reboot from the flash as it was left."""
    ready, crc = _store_ready_to_commit(NOMINAL)
    old = (2, banks.params_to_table(CAMERA), crc32(banks.params_to_table(CAMERA)))
    new = (3, banks.params_to_table(NOMINAL), crc)
    total = banks.SECTOR_BYTES + banks.BANK_RECORD_BYTES
    outcomes = {"old": 0, "new": 0}
    for budget in range(total):
        store = copy.deepcopy(ready)
        store.flash.power_budget = budget
        with pytest.raises(banks.PowerCut):
            commit(store, crc)
        active = banks.active_set(reboot(store))
        assert active in (old, new), budget
        outcomes["old" if active == old else "new"] += 1
    assert outcomes == {"old": total, "new": 0}  # the new record is valid only once its last byte (the CRC) is in
    store = copy.deepcopy(ready)
    store.flash.power_budget = total  # exactly enough: the commit completes
    assert commit(store, crc) == 3 and banks.active_set(reboot(store)) == new


def test_a_power_cut_at_every_byte_of_a_session_record_keeps_the_set_and_never_reissues_an_acked_nonce():
    ready = banks.factory_store(NOMINAL)
    first = banks.stage_begin(ready, TABLE_BYTES)
    first_counter = ready.nonce_counter
    for budget in range(banks.STAGE_RECORD_BYTES):
        store = copy.deepcopy(ready)
        store.flash.power_budget = budget
        with pytest.raises(banks.PowerCut):
            banks.stage_begin(store, TABLE_BYTES)
        again = reboot(store)
        assert banks.active_set(again)[0] == 1
        nonce = banks.stage_begin(again, TABLE_BYTES)
        assert again.nonce_counter > first_counter and nonce != first  # the acknowledged nonce is never given again


def test_a_full_session_area_rewrites_the_active_set_and_keeps_its_generation():
    store = banks.factory_store(NOMINAL)
    nonces = [banks.stage_begin(store, TABLE_BYTES) for _ in range(3 * banks.STAGE_SLOTS + 5)]
    assert len(set(nonces)) == len(nonces) and 0 not in nonces  # no repeat across rewrites
    assert store.nonce_counter == len(nonces)  # the counter behind them grew by one per session
    gen, table, _ = banks.active_set(store)
    assert (gen, table) == (1, banks.params_to_table(NOMINAL))
    again = reboot(store)
    assert banks.active_set(again)[:2] == (1, table) and again.epoch == store.epoch
    expected = banks.session_nonce(store.identity.uid, store.epoch, len(nonces) + 1)
    assert banks.stage_begin(again, TABLE_BYTES) == expected
    _, crc = stage(again, CAMERA)
    assert banks.stage_verify(again, crc) is None and commit(again, crc) == 2


def test_commit_needs_a_verified_set_with_the_same_crc():
    store = banks.factory_store(NOMINAL)
    table, crc = stage(store, CAMERA)
    assert commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.stage_verify(store, crc) is None
    assert commit(store, crc ^ 1).code == NakCode.NOT_VERIFIED
    assert banks.stage_chunk(store, 0, table[:4]) is None  # any chunk after verify un-verifies
    assert store.stage_state == StageState.RECEIVING
    assert commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.active_set(store)[0] == 1


def test_commit_needs_the_current_session_nonce_and_the_active_generation():
    store = banks.factory_store(NOMINAL)
    _, crc = stage(store, CAMERA)
    nonce = store.stage_nonce
    assert banks.stage_verify(store, crc) is None
    for wrong_nonce, expected in ((0, 1), (nonce - 1, 1), (nonce + 1, 1), (nonce, 0), (nonce, 2)):
        refusal = banks.commit(store, crc, wrong_nonce, expected)
        assert isinstance(refusal, banks.Refusal) and refusal.code == STALE, (wrong_nonce, expected)
    assert banks.commit(store, crc, nonce, 1) == 2
    assert banks.commit(store, crc, nonce, 1).code == STALE  # a session commits once
    assert banks.commit(store, crc, nonce, 2).code == STALE
    assert banks.active_set(store)[0] == 2


def test_a_new_session_voids_the_previous_nonce():
    store = banks.factory_store(NOMINAL)
    _, crc = stage(store, CAMERA)
    old_nonce = store.stage_nonce
    assert banks.stage_verify(store, crc) is None
    _, crc = stage(store, CAMERA)
    assert banks.stage_verify(store, crc) is None
    assert banks.commit(store, crc, old_nonce, 1).code == STALE
    assert banks.commit(store, crc, store.stage_nonce, 1) == 2


def test_a_corrupt_chunk_fails_the_crc_and_commits_nothing():
    store = banks.factory_store(NOMINAL)
    table = bytearray(banks.params_to_table(CAMERA))
    crc = crc32(bytes(table))
    table[5] ^= 0x10  # one bit flipped in transit
    stage(store, bytes(table))
    refusal = banks.stage_verify(store, crc)
    assert refusal.code == NakCode.BAD_CRC and "CRC" in refusal.text
    assert commit(store, crc).code == NakCode.NOT_VERIFIED
    assert banks.active_set(store)[0] == 1


def test_incomplete_and_out_of_bounds_staging_is_refused():
    store = banks.factory_store(NOMINAL)
    assert banks.stage_chunk(store, 0, b"x").code == NakCode.NOT_STAGED
    assert banks.stage_begin(store, TABLE_BYTES - 1).code == NakCode.BAD_LENGTH
    assert isinstance(banks.stage_begin(store, TABLE_BYTES), int)
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
    # generations are uint32 in the bank record: the commit after 2**32 - 1 must be a NAK, not an exception
    flash = banks.RamFlash()
    flash.program(0, banks.encode_bank_record(banks.BankRecord(5, 2**32 - 1, 0, banks.params_to_table(NOMINAL))))
    store = banks.boot(flash)
    _, crc = stage(store, CAMERA)
    assert banks.stage_verify(store, crc) is None
    before = store.flash.image.copy()
    refusal = commit(store, crc)
    assert isinstance(refusal, banks.Refusal) and refusal.code == NakCode.BANK_WRITE_FAILED
    assert np.array_equal(store.flash.image, before) and banks.active_set(store)[0] == 2**32 - 1


def test_a_power_cut_at_every_byte_of_a_session_area_rewrite_keeps_the_set_and_the_counter():
    """STAGE_BEGIN on a full session area rewrites the active set into the other sector (erase + bank record), then
    writes its session record: a cut after each of those 4224 bytes, each followed by a reboot."""
    ready = banks.factory_store(NOMINAL)
    for _ in range(banks.STAGE_SLOTS):
        banks.stage_begin(ready, TABLE_BYTES)
    issued = ready.nonce_counter
    factory = banks.active_set(ready)
    total = banks.SECTOR_BYTES + banks.BANK_RECORD_BYTES + banks.STAGE_RECORD_BYTES
    for budget in range(total):
        store = copy.deepcopy(ready)
        store.flash.power_budget = budget
        with pytest.raises(banks.PowerCut):
            banks.stage_begin(store, TABLE_BYTES)
        again = reboot(store)
        assert banks.active_set(again) == factory, budget
        banks.stage_begin(again, TABLE_BYTES)
        assert again.nonce_counter > issued, budget
