/* banks.c: onboard.banks in C (banks.h). */
#include "banks.h"

#include <string.h>

#include "st_messages.h"

#define BANK_MAGIC 0x324B4E42u  /* "BNK2" */
#define STAGE_MAGIC 0x32475453u /* "STG2" */
#define RESERVED_WORD 0xFFFFFFFFu
#define BANK_HEAD_BYTES 24u
#define STAGE_HEAD_BYTES 12u
#define NONCE_ROUNDS 4u
#define ROUND_MULTIPLIER 0x9E3779B1u

/* ------------------------------------------------------------------------------------------------- records */
void banks_encode_bank_record(const banks_record_t *record, uint8_t out[BANKS_BANK_RECORD_BYTES])
{
    st_put_u32(&out[0], BANK_MAGIC);
    st_put_u32(&out[4], record->seq);
    st_put_u32(&out[8], record->generation);
    st_put_u32(&out[12], record->nonce_counter);
    st_put_u32(&out[16], record->epoch);
    st_put_u32(&out[20], RESERVED_WORD);
    memcpy(&out[BANK_HEAD_BYTES], record->table, BANKS_TABLE_BYTES);
    st_put_u32(&out[BANKS_BANK_RECORD_BYTES - 4u], st_crc32(out, BANKS_BANK_RECORD_BYTES - 4u));
}

int banks_decode_bank_record(const uint8_t raw[BANKS_BANK_RECORD_BYTES], banks_record_t *record)
{
    if (st_get_u32(&raw[0]) != BANK_MAGIC ||
        st_crc32(raw, BANKS_BANK_RECORD_BYTES - 4u) != st_get_u32(&raw[BANKS_BANK_RECORD_BYTES - 4u])) {
        return 0;
    }
    record->seq = st_get_u32(&raw[4]);
    record->generation = st_get_u32(&raw[8]);
    record->nonce_counter = st_get_u32(&raw[12]);
    record->epoch = st_get_u32(&raw[16]);
    memcpy(record->table, &raw[BANK_HEAD_BYTES], BANKS_TABLE_BYTES);
    return 1;
}

void banks_encode_stage_record(uint32_t counter, uint32_t epoch, uint8_t out[BANKS_STAGE_RECORD_BYTES])
{
    st_put_u32(&out[0], STAGE_MAGIC);
    st_put_u32(&out[4], epoch);
    st_put_u32(&out[8], counter);
    st_put_u32(&out[12], st_crc32(out, STAGE_HEAD_BYTES));
}

int banks_decode_stage_record(const uint8_t raw[BANKS_STAGE_RECORD_BYTES], uint32_t *counter, uint32_t *epoch)
{
    if (st_get_u32(&raw[0]) != STAGE_MAGIC || st_crc32(raw, STAGE_HEAD_BYTES) != st_get_u32(&raw[12])) {
        return 0;
    }
    *epoch = st_get_u32(&raw[4]);
    *counter = st_get_u32(&raw[8]);
    return 1;
}

static int records_equal(const banks_record_t *a, const banks_record_t *b)
{
    return a->seq == b->seq && a->generation == b->generation && a->nonce_counter == b->nonce_counter &&
           a->epoch == b->epoch && memcmp(a->table, b->table, BANKS_TABLE_BYTES) == 0;
}

/* ---------------------------------------------------------------------------------------------------- nonce */
uint32_t banks_session_nonce(const uint8_t uid[BANKS_UID_BYTES], uint32_t epoch, uint32_t counter)
{
    uint8_t base[BANKS_UID_BYTES + 5u];
    uint32_t left = (counter >> 16u) & 0xFFFFu;
    uint32_t right = counter & 0xFFFFu;
    uint32_t i;
    memcpy(base, uid, BANKS_UID_BYTES);
    st_put_u32(&base[BANKS_UID_BYTES], epoch);
    for (i = 0u; i < NONCE_ROUNDS; ++i) {
        uint32_t key;
        uint32_t next;
        base[BANKS_UID_BYTES + 4u] = (uint8_t)i;
        key = st_crc32(base, sizeof base);
        next = left ^ ((((right ^ key) * ROUND_MULTIPLIER) & 0xFFFFFFFFu) >> 16u);
        left = right;
        right = next;
    }
    return (left << 16u) | right;
}

/* -------------------------------------------------------------------------------------------------- helpers */
static void refuse(banks_refusal_t *refusal, uint8_t code, const char *text)
{
    refusal->code = code;
    pyformat_init(&refusal->text);
    pyformat_str(&refusal->text, text);
}

static uint32_t stage_slot_address(uint32_t sector, uint32_t k)
{
    return sector * BANKS_SECTOR_BYTES + BANKS_BANK_RECORD_BYTES + k * BANKS_STAGE_RECORD_BYTES;
}

static uint32_t stage_sector(int32_t active) { return active == BANKS_NO_SLOT ? 1u : (uint32_t)active; }

static int first_free_stage_slot(const banks_hal_t *hal, uint32_t sector, uint32_t *free_slot)
{
    uint8_t raw[BANKS_STAGE_RECORD_BYTES];
    uint32_t k;
    uint32_t i;
    *free_slot = 0u;
    for (k = 0u; k < BANKS_STAGE_SLOTS; ++k) {
        if (hal->read(hal->ctx, stage_slot_address(sector, k), raw, BANKS_STAGE_RECORD_BYTES) != 0) {
            return BANKS_POWER_CUT;
        }
        for (i = 0u; i < BANKS_STAGE_RECORD_BYTES; ++i) {
            if (raw[i] != BANKS_ERASED_BYTE) {
                *free_slot = k + 1u;
                break;
            }
        }
    }
    return BANKS_OK;
}

static void clear_staging(banks_store_t *store)
{
    memset(store->staged, 0, sizeof store->staged);
    memset(store->received, 0, sizeof store->received);
    store->stage_state = ST_STAGE_EMPTY;
    store->verified_crc = 0u;
    store->stage_nonce = 0u;
}

static uint32_t draw_epoch(const banks_hal_t *hal)
{
    uint32_t e = hal->random32(hal->ctx);
    return e != 0u ? e : 1u;
}

/* ------------------------------------------------------------------------------------------------------ boot */
int banks_boot(banks_store_t *store, const banks_hal_t *hal, const params_limits_t *limits)
{
    uint8_t raw[BANKS_BANK_RECORD_BYTES];
    banks_record_t rec;
    uint32_t sector;
    uint32_t k;
    memset(store, 0, sizeof *store);
    store->hal = *hal;
    store->limits = *limits;
    store->active = BANKS_NO_SLOT;
    for (sector = 0u; sector < BANKS_N_SECTORS; ++sector) {
        if (hal->read(hal->ctx, sector * BANKS_SECTOR_BYTES, raw, BANKS_BANK_RECORD_BYTES) != 0) {
            return BANKS_POWER_CUT;
        }
        if (banks_decode_bank_record(raw, &rec)) {
            if (rec.nonce_counter > store->nonce_counter) {
                store->nonce_counter = rec.nonce_counter;
            }
            if (store->epoch == 0u) {
                store->epoch = rec.epoch;
            }
            if (!store->has_active_record || rec.seq > store->active_record.seq) {
                store->active = (int32_t)sector;
                store->active_record = rec;
                store->has_active_record = 1u;
            }
        }
        for (k = 0u; k < BANKS_STAGE_SLOTS; ++k) {
            uint32_t counter;
            uint32_t epoch;
            if (hal->read(hal->ctx, stage_slot_address(sector, k), raw, BANKS_STAGE_RECORD_BYTES) != 0) {
                return BANKS_POWER_CUT;
            }
            if (banks_decode_stage_record(raw, &counter, &epoch)) {
                if (counter > store->nonce_counter) {
                    store->nonce_counter = counter;
                }
                if (store->epoch == 0u) {
                    store->epoch = epoch;
                }
            }
        }
    }
    clear_staging(store);
    return first_free_stage_slot(hal, stage_sector(store->active), &store->stage_free);
}

int banks_factory(banks_store_t *store, const banks_hal_t *hal, const params_limits_t *limits,
                  const uint8_t table[BANKS_TABLE_BYTES])
{
    banks_record_t rec;
    uint8_t raw[BANKS_BANK_RECORD_BYTES];
    rec.seq = 1u;
    rec.generation = 1u;
    rec.nonce_counter = 0u;
    memcpy(rec.table, table, BANKS_TABLE_BYTES);
    rec.epoch = draw_epoch(hal);
    banks_encode_bank_record(&rec, raw);
    if (hal->erase(hal->ctx, 0u) != 0 || hal->program(hal->ctx, 0u, raw, BANKS_BANK_RECORD_BYTES) != 0) {
        return BANKS_POWER_CUT;
    }
    return banks_boot(store, hal, limits);
}

int banks_active_set(const banks_store_t *store, uint32_t *generation, uint8_t table[BANKS_TABLE_BYTES],
                     uint32_t *crc)
{
    if (!store->has_active_record) {
        return 0;
    }
    *generation = store->active_record.generation;
    memcpy(table, store->active_record.table, BANKS_TABLE_BYTES);
    *crc = st_crc32(store->active_record.table, BANKS_TABLE_BYTES);
    return 1;
}

static uint32_t active_generation(const banks_store_t *store)
{
    return store->has_active_record ? store->active_record.generation : 0u;
}

/* erase the inactive sector, program `record`, read it back, switch */
static int write_bank(banks_store_t *store, const banks_record_t *record, banks_refusal_t *refusal)
{
    const banks_hal_t *hal = &store->hal;
    const uint32_t target = store->active == BANKS_NO_SLOT ? 0u : 1u - (uint32_t)store->active;
    uint8_t raw[BANKS_BANK_RECORD_BYTES];
    banks_record_t back;
    banks_encode_bank_record(record, raw);
    if (hal->erase(hal->ctx, target) != 0 ||
        hal->program(hal->ctx, target * BANKS_SECTOR_BYTES, raw, BANKS_BANK_RECORD_BYTES) != 0 ||
        hal->read(hal->ctx, target * BANKS_SECTOR_BYTES, raw, BANKS_BANK_RECORD_BYTES) != 0) {
        return BANKS_POWER_CUT;
    }
    if (!banks_decode_bank_record(raw, &back) || !records_equal(&back, record)) {
        refuse(refusal, ST_NAK_BANK_WRITE_FAILED, target == 0u ? "sector A" : "sector B");
        pyformat_str(&refusal->text, " did not read back intact; nothing switched");
        return BANKS_REFUSED;
    }
    store->active = (int32_t)target; /* the atomic switch */
    store->active_record = *record;
    store->has_active_record = 1u;
    store->stage_free = 0u;
    return BANKS_OK;
}

/* --------------------------------------------------------------------------------------------------- staging */
int banks_stage_begin(banks_store_t *store, uint32_t length, uint32_t *nonce, banks_refusal_t *refusal)
{
    const banks_hal_t *hal = &store->hal;
    uint8_t raw[BANKS_STAGE_RECORD_BYTES];
    uint64_t counter;
    uint32_t value;
    uint32_t address;
    uint32_t back_counter;
    uint32_t back_epoch;
    int result;
    if (length != BANKS_TABLE_BYTES) {
        refuse(refusal, ST_NAK_BAD_LENGTH, "a parameter table is 92 bytes, not ");
        pyformat_u64(&refusal->text, length);
        return BANKS_REFUSED;
    }
    clear_staging(store);
    if (store->nonce_counter >= BANKS_MAX_COUNTER) {
        refuse(refusal, ST_NAK_BANK_WRITE_FAILED, "staging-session counter exhausted at 4294967295");
        return BANKS_REFUSED;
    }
    if (store->stage_free >= BANKS_STAGE_SLOTS && store->has_active_record) {
        banks_record_t rec = store->active_record; /* no room: rewrite the active set into the other sector */
        if (rec.seq >= BANKS_MAX_COUNTER) {
            refuse(refusal, ST_NAK_BANK_WRITE_FAILED, "bank sequence counter exhausted at 4294967295");
            return BANKS_REFUSED;
        }
        rec.seq += 1u;
        rec.nonce_counter = store->nonce_counter;
        result = write_bank(store, &rec, refusal);
        if (result != BANKS_OK) {
            return result;
        }
    } else if (store->stage_free >= BANKS_STAGE_SLOTS) { /* blank flash, stage sector full: start it again */
        if (hal->erase(hal->ctx, stage_sector(store->active)) != 0) {
            return BANKS_POWER_CUT;
        }
        store->stage_free = 0u;
    }
    if (store->epoch == 0u) { /* the flash holds no record: a new epoch */
        store->epoch = draw_epoch(hal);
    }
    counter = (uint64_t)store->nonce_counter + 1u;
    value = banks_session_nonce(hal->uid, store->epoch, (uint32_t)counter);
    if (value == 0u) { /* 0 means "no session": the one counter mapped there is skipped */
        counter += 1u;
        value = banks_session_nonce(hal->uid, store->epoch, (uint32_t)counter);
    }
    if (counter > BANKS_MAX_COUNTER) {
        refuse(refusal, ST_NAK_BANK_WRITE_FAILED, "staging-session counter exhausted at 4294967295");
        return BANKS_REFUSED;
    }
    address = stage_slot_address(stage_sector(store->active), store->stage_free);
    store->stage_free += 1u; /* a half-written slot stays used */
    banks_encode_stage_record((uint32_t)counter, store->epoch, raw);
    if (hal->program(hal->ctx, address, raw, BANKS_STAGE_RECORD_BYTES) != 0 ||
        hal->read(hal->ctx, address, raw, BANKS_STAGE_RECORD_BYTES) != 0) {
        return BANKS_POWER_CUT;
    }
    if (!banks_decode_stage_record(raw, &back_counter, &back_epoch) || back_counter != (uint32_t)counter ||
        back_epoch != store->epoch) {
        refuse(refusal, ST_NAK_BANK_WRITE_FAILED, "the staging-session record did not read back; try again");
        return BANKS_REFUSED;
    }
    store->nonce_counter = (uint32_t)counter;
    store->stage_nonce = value;
    store->stage_state = ST_STAGE_RECEIVING;
    *nonce = value;
    return BANKS_OK;
}

int banks_stage_chunk(banks_store_t *store, uint32_t offset, const uint8_t *data, uint32_t n,
                      banks_refusal_t *refusal)
{
    if (store->stage_state == ST_STAGE_EMPTY) {
        refuse(refusal, ST_NAK_NOT_STAGED, "no upload in progress (send STAGE_BEGIN first)");
        return BANKS_REFUSED;
    }
    if (n == 0u || (uint64_t)offset + n > BANKS_TABLE_BYTES) {
        refuse(refusal, ST_NAK_BAD_LENGTH, "chunk of ");
        pyformat_u64(&refusal->text, n);
        pyformat_str(&refusal->text, " bytes at offset ");
        pyformat_u64(&refusal->text, offset);
        pyformat_str(&refusal->text, " is outside the 92-byte table");
        return BANKS_REFUSED;
    }
    memcpy(&store->staged[offset], data, n);
    memset(&store->received[offset], 1, n);
    store->stage_state = ST_STAGE_RECEIVING;
    store->verified_crc = 0u;
    return BANKS_OK;
}

static uint32_t missing_bytes(const banks_store_t *store)
{
    uint32_t i;
    uint32_t missing = 0u;
    if (store->stage_state == ST_STAGE_EMPTY) {
        return BANKS_TABLE_BYTES;
    }
    for (i = 0u; i < BANKS_TABLE_BYTES; ++i) {
        missing += store->received[i] ? 0u : 1u;
    }
    return missing;
}

int banks_stage_verify(banks_store_t *store, uint32_t crc, banks_refusal_t *refusal)
{
    const uint32_t missing = missing_bytes(store);
    uint32_t actual;
    if (missing != 0u) {
        refuse(refusal, ST_NAK_NOT_STAGED, "staged set incomplete (");
        pyformat_u64(&refusal->text, missing);
        pyformat_str(&refusal->text, " of 92 bytes missing)");
        return BANKS_REFUSED;
    }
    actual = st_crc32(store->staged, BANKS_TABLE_BYTES);
    if (actual != crc) {
        store->stage_state = ST_STAGE_RECEIVING;
        refuse(refusal, ST_NAK_BAD_CRC, "staged set has CRC 0x");
        pyformat_hex08(&refusal->text, actual);
        pyformat_str(&refusal->text, ", host sent 0x");
        pyformat_hex08(&refusal->text, crc);
        return BANKS_REFUSED;
    }
    if (params_check_table(store->staged, &store->limits, &refusal->text)) {
        store->stage_state = ST_STAGE_RECEIVING;
        refusal->code = ST_NAK_INVALID_PARAMS;
        return BANKS_REFUSED;
    }
    store->stage_state = ST_STAGE_VERIFIED;
    store->verified_crc = actual;
    return BANKS_OK;
}

int banks_staged_set(const banks_store_t *store, uint8_t table[BANKS_TABLE_BYTES], uint32_t *crc)
{
    if (missing_bytes(store) != 0u) {
        return 0;
    }
    memcpy(table, store->staged, BANKS_TABLE_BYTES);
    *crc = st_crc32(store->staged, BANKS_TABLE_BYTES);
    return 1;
}

int banks_commit(banks_store_t *store, uint32_t crc, uint32_t nonce, uint32_t expected_generation,
                 uint32_t *generation, banks_refusal_t *refusal)
{
    const uint32_t current = active_generation(store);
    uint64_t next_generation;
    uint64_t seq;
    banks_record_t rec;
    int result;
    if (store->stage_nonce == 0u || nonce != store->stage_nonce) {
        refuse(refusal, ST_NAK_STALE_SESSION, "nonce ");
        pyformat_u64(&refusal->text, nonce);
        pyformat_str(&refusal->text, " is not the current staging session's; nothing switched");
        return BANKS_REFUSED;
    }
    if (expected_generation != current) {
        refuse(refusal, ST_NAK_STALE_SESSION, "expected generation ");
        pyformat_u64(&refusal->text, expected_generation);
        pyformat_str(&refusal->text, " but generation ");
        pyformat_u64(&refusal->text, current);
        pyformat_str(&refusal->text, " is active; nothing switched");
        return BANKS_REFUSED;
    }
    if (store->stage_state != ST_STAGE_VERIFIED) {
        refuse(refusal, ST_NAK_NOT_VERIFIED, "the staged set has not passed STAGE_VERIFY");
        return BANKS_REFUSED;
    }
    if (crc != store->verified_crc || st_crc32(store->staged, BANKS_TABLE_BYTES) != crc) {
        refuse(refusal, ST_NAK_NOT_VERIFIED, "CRC 0x");
        pyformat_hex08(&refusal->text, crc);
        pyformat_str(&refusal->text, " is not that of the verified staged set 0x");
        pyformat_hex08(&refusal->text, store->verified_crc);
        return BANKS_REFUSED;
    }
    next_generation = (uint64_t)current + 1u;
    seq = store->has_active_record ? (uint64_t)store->active_record.seq + 1u : 1u;
    if (next_generation > BANKS_MAX_COUNTER || seq > BANKS_MAX_COUNTER) {
        refuse(refusal, ST_NAK_BANK_WRITE_FAILED, "generation counter exhausted at 4294967295; nothing switched");
        return BANKS_REFUSED;
    }
    rec.seq = (uint32_t)seq;
    rec.generation = (uint32_t)next_generation;
    rec.nonce_counter = store->nonce_counter;
    rec.epoch = store->epoch;
    memcpy(rec.table, store->staged, BANKS_TABLE_BYTES);
    result = write_bank(store, &rec, refusal);
    if (result != BANKS_OK) {
        return result;
    }
    clear_staging(store); /* the session is used up */
    *generation = rec.generation;
    return BANKS_OK;
}
