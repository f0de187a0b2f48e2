/* ram_flash.c: onboard.banks.RamFlash in C (ram_flash.h). */
#include "ram_flash.h"

#include <string.h>

void ram_flash_erase_all(ram_flash_t *flash)
{
    memset(flash->image, (int)BANKS_ERASED_BYTE, sizeof flash->image);
    flash->power_budget = RAM_FLASH_NO_CUT;
    flash->misuse = 0u;
}

/* bytes of `wanted` the power allows; the budget spent */
static uint32_t allowed(ram_flash_t *flash, uint32_t wanted)
{
    uint32_t n = wanted;
    if (flash->power_budget == RAM_FLASH_NO_CUT) {
        return n;
    }
    if ((uint32_t)flash->power_budget < n) {
        n = (uint32_t)flash->power_budget;
    }
    flash->power_budget -= (int32_t)n;
    return n;
}

static int ram_read(void *ctx, uint32_t address, uint8_t *out, uint32_t n)
{
    ram_flash_t *const flash = (ram_flash_t *)ctx;
    if (address > BANKS_FLASH_BYTES || n > BANKS_FLASH_BYTES - address) {
        flash->misuse = 1u;
        return 1;
    }
    memcpy(out, &flash->image[address], n);
    return 0;
}

static int ram_erase(void *ctx, uint32_t sector)
{
    ram_flash_t *const flash = (ram_flash_t *)ctx;
    uint32_t n;
    if (sector >= BANKS_N_SECTORS) {
        flash->misuse = 1u;
        return 1;
    }
    n = allowed(flash, BANKS_SECTOR_BYTES);
    memset(&flash->image[sector * BANKS_SECTOR_BYTES], (int)BANKS_ERASED_BYTE, n);
    return n == BANKS_SECTOR_BYTES ? 0 : 1;
}

static int ram_program(void *ctx, uint32_t address, const uint8_t *data, uint32_t n)
{
    ram_flash_t *const flash = (ram_flash_t *)ctx;
    uint32_t done;
    uint32_t i;
    if (address % BANKS_WRITE_BYTES != 0u || n % BANKS_WRITE_BYTES != 0u || address > BANKS_FLASH_BYTES ||
        n > BANKS_FLASH_BYTES - address) {
        flash->misuse = 1u; /* onboard.banks.nor_program's ValueError: a programming error, never done */
        return 1;
    }
    done = allowed(flash, n);
    for (i = 0u; i < done; ++i) {
        flash->image[address + i] = (uint8_t)(flash->image[address + i] & data[i]);
    }
    return done == n ? 0 : 1;
}

void ram_flash_hal(ram_flash_t *flash, uint32_t (*random32)(void *ctx), const uint8_t uid[BANKS_UID_BYTES],
                   banks_hal_t *hal)
{
    hal->ctx = flash;
    hal->read = ram_read;
    hal->erase = ram_erase;
    hal->program = ram_program;
    hal->random32 = random32;
    memcpy(hal->uid, uid, BANKS_UID_BYTES);
}
