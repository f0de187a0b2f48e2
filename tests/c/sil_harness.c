/* sil_harness.c: the C firmware core run standalone (software in the loop) for the sanitizer test
 * (tests/test_firmware_c.py): the core's RAM NOR flash behind the HAL (ram_flash.c: erase to 0xFF, program clears
 * bits in whole 8-byte units, a power budget that cuts an operation part-way), a seeded generator of commands
 * (uploads, refused and mutated commands, random bytes), power cuts and reboots. Every reply must decode; a NOR rule
 * broken by the core (a call outside the flash, a program that is not whole aligned units) stops the run with exit
 * status 1. Usage: sil N [fuzz]: N commands; with "fuzz" every one of them is mutated (a byte changed, cut, or
 * random bytes after its type byte). */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "firmware.h"
#include "ram_flash.h"
#include "st_messages.h"

static ram_flash_t flash; /* the core's example HAL (ram_flash.c): NOR rules, a power budget in bytes */
static uint32_t rng_state = 12345u;

static uint32_t next_random(void)
{
    rng_state ^= rng_state << 13u;
    rng_state ^= rng_state >> 17u;
    rng_state ^= rng_state << 5u;
    return rng_state;
}

/* a flash call that broke the NOR rules (outside the flash, not whole aligned units) stops the run */
static void check_flash_use(void)
{
    if (flash.misuse) {
        fprintf(stderr, "a flash call broke the NOR rules (outside the flash or not whole aligned units)\n");
        exit(1);
    }
}

static uint32_t hal_random(void *ctx)
{
    (void)ctx;
    return next_random();
}

static firmware_t fw;

static void boot(void)
{
    banks_hal_t hal;
    banks_store_t store;
    uint8_t uid[BANKS_UID_BYTES];
    params_limits_t limits = params_default_limits(70.0);
    firmware_budget_t b = firmware_default_budget();
    memset(uid, 0x5A, sizeof uid);
    ram_flash_hal(&flash, hal_random, uid, &hal);
    if (banks_boot(&store, &hal, &limits) != BANKS_OK || firmware_init(&fw, &store, NULL, NULL, &b) != 0) {
        fprintf(stderr, "boot failed\n");
        exit(1);
    }
    check_flash_use();
}

static void good_table(uint8_t table[ST_PARAM_TABLE_BYTES], uint32_t variant)
{
    float v[ST_PARAM_N_FIELDS];
    uint32_t i;
    for (i = 0u; i < ST_PARAM_N_FIELDS; ++i) {
        v[i] = i >= ST_PARAM_SIGMA_OFFSET ? NAN : 0.0f;
    }
    v[ST_PARAM_FOCAL_LENGTH_MM] = 70.0f;
    v[ST_PARAM_PIXEL_PITCH_UM] = 12.0f;
    v[ST_PARAM_PRINCIPAL_POINT_X_PX] = 511.5f;
    v[ST_PARAM_PRINCIPAL_POINT_Y_PX] = 511.5f;
    v[ST_PARAM_IMAGE_WIDTH_PX] = 1024.0f;
    v[ST_PARAM_IMAGE_HEIGHT_PX] = 1024.0f;
    v[ST_PARAM_K1] = -1e-9f * (float)(variant % 3u);
    if (variant % 5u == 4u) { /* a field at a random value: most such sets are refused, with numbers in the text */
        uint32_t bits = next_random();
        float x;
        memcpy(&x, &bits, sizeof x);
        v[next_random() % ST_PARAM_N_FIELDS] = x;
    }
    st_param_table_encode(v, table);
}

int main(int argc, char **argv)
{
    const long n_commands = argc > 1 ? atol(argv[1]) : 10000;
    const int fuzz_all = argc > 2 && strcmp(argv[2], "fuzz") == 0;
    uint8_t buf[ST_MSG_MAX_BYTES];
    uint8_t reply[FIRMWARE_REPLY_MAX_BYTES];
    uint8_t table[ST_PARAM_TABLE_BYTES];
    st_message_t cmd;
    st_message_t back;
    uint32_t nonce = 0u;
    long k;
    long answered = 0, undecodable = 0, cuts = 0, commits = 0;
    ram_flash_erase_all(&flash);
    boot();
    good_table(table, 0u);
    for (k = 0; k < n_commands; ++k) {
        const uint32_t kind = next_random() % 12u;
        const uint32_t a = next_random();
        size_t n;
        size_t reply_len = 0u;
        int result;
        memset(&cmd, 0, sizeof cmd);
        switch (kind) {
        case 0: cmd.type = ST_MSG_GET_STATUS; break;
        case 1:
            cmd.type = ST_MSG_STAGE_BEGIN;
            cmd.u.stage_begin.length = (uint16_t)(a % 8u == 0u ? a % 200u : ST_PARAM_TABLE_BYTES);
            good_table(table, a);
            break;
        case 2:
        case 3:
            cmd.type = ST_MSG_STAGE_CHUNK;
            cmd.u.stage_chunk.offset = (uint16_t)(kind == 2 ? 0u : a % 100u);
            cmd.u.stage_chunk.n_bytes = (uint8_t)(kind == 2 ? ST_PARAM_TABLE_BYTES : (a >> 8u) % 60u);
            if ((uint32_t)cmd.u.stage_chunk.offset < ST_PARAM_TABLE_BYTES) {
                uint32_t avail = ST_PARAM_TABLE_BYTES - cmd.u.stage_chunk.offset;
                memcpy(cmd.u.stage_chunk.data, &table[cmd.u.stage_chunk.offset],
                       cmd.u.stage_chunk.n_bytes < avail ? cmd.u.stage_chunk.n_bytes : avail);
            }
            break;
        case 4:
            cmd.type = ST_MSG_STAGE_VERIFY;
            cmd.u.stage_verify.crc32 = a % 4u ? st_crc32(table, ST_PARAM_TABLE_BYTES) : a;
            break;
        case 5: cmd.type = ST_MSG_READ_STAGED; break;
        case 6:
        case 7:
            cmd.type = ST_MSG_COMMIT;
            cmd.u.commit.crc32 = st_crc32(table, ST_PARAM_TABLE_BYTES);
            cmd.u.commit.nonce = a % 5u ? nonce : a;
            cmd.u.commit.expected_generation = fw.store.has_active_record ? fw.store.active_record.generation : 0u;
            break;
        case 8: cmd.type = ST_MSG_READ_ACTIVE; break;
        case 9: cmd.type = ST_MSG_READ_ESTIMATE; break;
        case 10:
            cmd.type = ST_MSG_STREAM_CONTROL;
            cmd.u.stream_control.enable = (uint8_t)(a & 1u);
            break;
        default:
            cmd.type = ST_MSG_END_OF_STREAM;
            break;
        }
        n = st_encode(&cmd, buf, sizeof buf);
        if (n == 0u) {
            fprintf(stderr, "encode failed for type %u\n", cmd.type);
            return 1;
        }
        if (fuzz_all || a % 7u == 0u) { /* a mutated message: a byte changed, cut, or random bytes after the type */
            buf[next_random() % n] = (uint8_t)next_random();
            if (a % 3u == 0u) {
                n = next_random() % (n + 1u);
            } else if (fuzz_all && a % 3u == 1u) {
                size_t i;
                n = 1u + next_random() % 300u;
                for (i = 1u; i < n; ++i) {
                    buf[i] = (uint8_t)next_random();
                }
            }
        }
        if (a % 97u == 1u) { /* a power cut somewhere in this command's flash writes */
            flash.power_budget = (int32_t)(next_random() % (BANKS_SECTOR_BYTES + 200u));
        }
        result = firmware_handle(&fw, buf, n, reply, sizeof reply, &reply_len);
        flash.power_budget = RAM_FLASH_NO_CUT;
        check_flash_use();
        if (result == FIRMWARE_POWER_CUT || a % 211u == 5u) {
            cuts += result == FIRMWARE_POWER_CUT;
            boot();
            continue;
        }
        if (result == FIRMWARE_UNDECODABLE) {
            continue;
        }
        if (result != FIRMWARE_REPLY || st_decode(reply, reply_len, &back) != ST_OK) {
            undecodable += 1;
            continue;
        }
        answered += 1;
        if (back.type == ST_MSG_ACK && back.u.ack.command == ST_MSG_STAGE_BEGIN) {
            nonce = back.u.ack.value;
        }
        if (back.type == ST_MSG_ACK && back.u.ack.command == ST_MSG_COMMIT) {
            commits += 1;
        }
    }
    printf("commands %ld answered %ld commits %ld power cuts %ld replies %ld undecodable\n", n_commands, answered,
           commits, cuts, undecodable);
    return 0;
}
