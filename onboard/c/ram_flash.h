/* ram_flash.h: NOR flash held in RAM behind the banks HAL, the C form of onboard.banks.RamFlash: the example HAL of
 * the firmware core and the flash of a host build (tests, a simulator, a first bring-up before the flash driver).
 *
 * The NOR rules of onboard.banks.nor_erase / nor_program: erase sets a sector to 0xFF byte by byte in address order,
 * program only clears bits (new = old & data) of whole, aligned BANKS_WRITE_BYTES units. power_budget: bytes that may
 * still be erased or programmed before the power fails (RAM_FLASH_NO_CUT: never), so a test can cut an operation at
 * any byte; the call then returns nonzero and the core stops (BANKS_POWER_CUT) with what was done in the image.
 *
 * A real part replaces the three flash calls by its vendor driver (read: memcpy from the memory-mapped flash; erase
 * and program: the driver, blocking until done, never returning on a real power loss), random32 by its TRNG and uid
 * by its unique ID. */
#ifndef RAM_FLASH_H
#define RAM_FLASH_H

#include <stdint.h>

#include "banks.h"

#ifdef __cplusplus
extern "C" {
#endif

#define RAM_FLASH_NO_CUT (-1)

typedef struct {
    uint8_t image[BANKS_FLASH_BYTES];
    int32_t power_budget; /* bytes still allowed, RAM_FLASH_NO_CUT = the power never fails */
    uint32_t misuse;      /* set when a call broke the NOR rules (outside the flash, not whole units) */
} ram_flash_t;

/* An erased flash (every byte 0xFF), the power never failing. */
void ram_flash_erase_all(ram_flash_t *flash);
/* The HAL over `flash`: its read, erase and program, the caller's random source (called with ctx = flash) and uid. */
void ram_flash_hal(ram_flash_t *flash, uint32_t (*random32)(void *ctx), const uint8_t uid[BANKS_UID_BYTES],
                   banks_hal_t *hal);

#ifdef __cplusplus
}
#endif
#endif /* RAM_FLASH_H */
