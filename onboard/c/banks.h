/* banks.h: the sensor's parameter banks, the C form of onboard.banks: a RAM staging area and two NOR-flash sectors
 * (A/B) switched atomically, with a persisted staging-session counter and a device- and epoch-keyed nonce.
 *
 * Flash (through banks_hal_t, the platform's callbacks): BANKS_N_SECTORS sectors of BANKS_SECTOR_BYTES; erase sets a
 * sector to 0xFF, program only clears bits (new = old & data) in aligned units of BANKS_WRITE_BYTES; a power cut may
 * stop either after any byte. Records, little-endian, each closed by a CRC-32 over the bytes before it:
 *   bank  (120 bytes, offset 0 of a sector): "BNK2" seq generation nonce_counter epoch 0xFFFFFFFF table[92] crc
 *   stage (16 bytes, after the active sector's bank record): "STG2" epoch counter crc
 * Boot, commit, the session-area rewrite, the nonce (banks_session_nonce: a 4-round Feistel permutation of the
 * counter keyed by the device uid and the flash epoch) and every refusal text are the reference's (onboard/banks.py
 * explains each rule); tests/test_firmware_c.py proves the same replies and the same flash bytes.
 *
 * Results: BANKS_OK, BANKS_REFUSED (the refusal's code and text filled), BANKS_POWER_CUT (a HAL call reported that
 * the power failed part-way: the device stops here; what is in flash is what a reboot finds). */
#ifndef BANKS_H
#define BANKS_H

#include <stdint.h>

#include "params.h"
#include "pyformat.h"
#include "st_param_table.h"

#ifdef __cplusplus
extern "C" {
#endif

#define BANKS_N_SECTORS 2u
#define BANKS_SECTOR_BYTES 4096u
#define BANKS_WRITE_BYTES 8u
#define BANKS_FLASH_BYTES (BANKS_N_SECTORS * BANKS_SECTOR_BYTES)
#define BANKS_ERASED_BYTE 0xFFu
#define BANKS_NO_SLOT (-1)
#define BANKS_MAX_COUNTER 0xFFFFFFFFu
#define BANKS_BANK_RECORD_BYTES 120u
#define BANKS_STAGE_RECORD_BYTES 16u
#define BANKS_STAGE_SLOTS ((BANKS_SECTOR_BYTES - BANKS_BANK_RECORD_BYTES) / BANKS_STAGE_RECORD_BYTES)
#define BANKS_UID_BYTES 12u
#define BANKS_TABLE_BYTES ST_PARAM_TABLE_BYTES

enum banks_result { BANKS_OK = 0, BANKS_REFUSED = 1, BANKS_POWER_CUT = 2 };

/* The platform: flash and identity. Every flash callback returns 0 when the operation completed, nonzero when the
 * power failed during it (a modelled cut; a real device simply never returns). program: whole write units. */
typedef struct {
    void *ctx;
    int (*read)(void *ctx, uint32_t address, uint8_t *out, uint32_t n);
    int (*erase)(void *ctx, uint32_t sector);
    int (*program)(void *ctx, uint32_t address, const uint8_t *data, uint32_t n);
    uint32_t (*random32)(void *ctx); /* the hardware random source; drawn only for a new flash epoch */
    uint8_t uid[BANKS_UID_BYTES];    /* the MCU's unique ID */
} banks_hal_t;

typedef struct {
    uint32_t seq;
    uint32_t generation;
    uint32_t nonce_counter;
    uint32_t epoch;
    uint8_t table[BANKS_TABLE_BYTES];
} banks_record_t;

typedef struct {
    uint8_t code; /* NakCode */
    pyformat_text_t text;
} banks_refusal_t;

/* onboard.banks.BankStore */
typedef struct {
    banks_hal_t hal;
    params_limits_t limits;
    int32_t active; /* sector of the active bank record, BANKS_NO_SLOT before the first commit */
    uint32_t has_active_record;
    banks_record_t active_record;
    uint32_t nonce_counter;
    uint32_t stage_free;
    uint8_t staged[BANKS_TABLE_BYTES];
    uint8_t received[BANKS_TABLE_BYTES];
    uint8_t stage_state; /* StageState */
    uint32_t verified_crc;
    uint32_t stage_nonce;
    uint32_t epoch;
} banks_store_t;

void banks_encode_bank_record(const banks_record_t *record, uint8_t out[BANKS_BANK_RECORD_BYTES]);
int banks_decode_bank_record(const uint8_t raw[BANKS_BANK_RECORD_BYTES], banks_record_t *record); /* 1 = valid */
void banks_encode_stage_record(uint32_t counter, uint32_t epoch, uint8_t out[BANKS_STAGE_RECORD_BYTES]);
int banks_decode_stage_record(const uint8_t raw[BANKS_STAGE_RECORD_BYTES], uint32_t *counter, uint32_t *epoch);
uint32_t banks_session_nonce(const uint8_t uid[BANKS_UID_BYTES], uint32_t epoch, uint32_t counter);

/* Start-up (onboard.banks.boot). BANKS_OK, or BANKS_POWER_CUT if a read failed. */
int banks_boot(banks_store_t *store, const banks_hal_t *hal, const params_limits_t *limits);
/* onboard.banks.factory_store's flash writes: `table` as generation 1 in sector A under a new epoch (the caller
 * validated it), then boot. */
int banks_factory(banks_store_t *store, const banks_hal_t *hal, const params_limits_t *limits,
                  const uint8_t table[BANKS_TABLE_BYTES]);
/* (generation, table, crc32) of the active set: 1, or 0 before the first commit */
int banks_active_set(const banks_store_t *store, uint32_t *generation, uint8_t table[BANKS_TABLE_BYTES],
                     uint32_t *crc);
int banks_stage_begin(banks_store_t *store, uint32_t length, uint32_t *nonce, banks_refusal_t *refusal);
int banks_stage_chunk(banks_store_t *store, uint32_t offset, const uint8_t *data, uint32_t n,
                      banks_refusal_t *refusal);
int banks_stage_verify(banks_store_t *store, uint32_t crc, banks_refusal_t *refusal);
/* (table, crc32) of a complete staged set: 1, else 0 */
int banks_staged_set(const banks_store_t *store, uint8_t table[BANKS_TABLE_BYTES], uint32_t *crc);
int banks_commit(banks_store_t *store, uint32_t crc, uint32_t nonce, uint32_t expected_generation,
                 uint32_t *generation, banks_refusal_t *refusal);

#ifdef __cplusplus
}
#endif
#endif /* BANKS_H */
