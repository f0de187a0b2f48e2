/* cortexm_glue.c: the platform glue of the C firmware core on an emulated Cortex-M (hostlink/portkit/cortexm.py,
 * `hostlink costs --target`). Not part of the core (onboard/c): what a board support package provides.
 *
 * - frexp, hypot, hypotf, nearbyint: the C library functions the core calls that neither the toolchain's compiler
 *   runtime (sqrt, sin, cos, tan, floor, ceil, round, fabs, fmodf, memcpy, memset) nor the musl sources built beside
 *   it (pow, ldexp) supply, written from C99 7.12 and the IEEE-754 binary64 layout. Where the core calls them:
 *   frexp in fixedpoint.c (exact), hypot of two whole pixel counts in recursive.c (the squares' sum is exact: so is
 *   the rounded square root), hypotf in params.c (float32 operands squared and summed in double are exact up to one
 *   rounding: the result is hypot's float32 value but for double rounding, which a 2^-29 relative margin makes a
 *   2^-29-probability event), nearbyint in firmware.c (round to nearest even, the default rounding mode).
 * - The flash HAL (banks_hal_t) over a NOR device mapped at CORTEXM_FLASH_DEVICE: reads copy, erase sets a sector
 *   to 0xFF, program clears bits (NOR: new = old AND data), as onboard.banks.RamFlash does; counters of the
 *   operations for the cost table.
 * - cortexm_return: where every call made by the host returns (the emulator stops there). */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "banks.h"

/* The flash device's address: outside the image's flash and RAM (the emulator maps it separately). */
#define CORTEXM_FLASH_DEVICE ((uint8_t *)0x60000000u)

double frexp(double x, int *e);

double frexp(double x, int *e)
{
    uint64_t bits;
    int exponent;
    memcpy(&bits, &x, sizeof bits);
    exponent = (int)((bits >> 52) & 0x7FFu);
    if (exponent == 0) {
        if ((bits << 1) == 0u) { /* +-0 */
            *e = 0;
            return x;
        }
        /* subnormal: scale into the normal range by 2^64 first */
        x = frexp(x * 18446744073709551616.0, e);
        *e -= 64;
        return x;
    }
    if (exponent == 0x7FF) { /* inf, NaN: returned, exponent unspecified */
        *e = 0;
        return x;
    }
    *e = exponent - 1022;
    bits = (bits & ~((uint64_t)0x7FFu << 52)) | ((uint64_t)1022u << 52);
    memcpy(&x, &bits, sizeof x);
    return x;
}

double hypot(double x, double y);
float hypotf(float x, float y);
double nearbyint(double x);

double hypot(double x, double y)
{
    /* scaled by a power of two (exact) when a square would overflow or underflow */
    const double ax = fabs(x), ay = fabs(y);
    const double big = ax > ay ? ax : ay, small = ax > ay ? ay : ax;
    double scale = 1.0;
    if (big != big || small != small) {
        return (big == INFINITY || small == INFINITY) ? INFINITY : x + y;
    }
    if (big == INFINITY) {
        return INFINITY;
    }
    if (big > 0x1p500) {
        scale = 0x1p600;
    } else if (small < 0x1p-500 && big < 0x1p-500) {
        scale = 0x1p-600;
    }
    {
        const double a = big / scale, b = small / scale;
        return sqrt(a * a + b * b) * scale;
    }
}

float hypotf(float x, float y)
{
    const double a = (double)x, b = (double)y;
    return (float)sqrt(a * a + b * b);
}

double nearbyint(double x)
{
    const double two52 = 4503599627370496.0; /* 2^52: adding and removing it rounds to a whole number, ties even */
    if (!(fabs(x) < two52)) {
        return x; /* already whole, or inf or NaN */
    }
    if (x > 0.0) {
        return (x + two52) - two52;
    }
    if (x < 0.0) {
        const double r = (x - two52) + two52;
        return r == 0.0 ? -0.0 : r;
    }
    return x; /* +-0 */
}

/* Flash operations since the last reset (read by the host). */
volatile uint32_t cortexm_flash_erases;
volatile uint32_t cortexm_flash_programmed_bytes;

int cortexm_flash_read(void *ctx, uint32_t address, uint8_t *out, uint32_t n);
int cortexm_flash_erase(void *ctx, uint32_t sector);
int cortexm_flash_program(void *ctx, uint32_t address, const uint8_t *data, uint32_t n);
uint32_t cortexm_random32(void *ctx);
void cortexm_return(void);

int cortexm_flash_read(void *ctx, uint32_t address, uint8_t *out, uint32_t n)
{
    (void)ctx;
    memcpy(out, CORTEXM_FLASH_DEVICE + address, n);
    return 0;
}

int cortexm_flash_erase(void *ctx, uint32_t sector)
{
    (void)ctx;
    memset(CORTEXM_FLASH_DEVICE + (size_t)sector * BANKS_SECTOR_BYTES, 0xFF, BANKS_SECTOR_BYTES);
    cortexm_flash_erases += 1u;
    return 0;
}

int cortexm_flash_program(void *ctx, uint32_t address, const uint8_t *data, uint32_t n)
{
    uint32_t i;
    (void)ctx;
    for (i = 0u; i < n; ++i) {
        CORTEXM_FLASH_DEVICE[address + i] = (uint8_t)(CORTEXM_FLASH_DEVICE[address + i] & data[i]);
    }
    cortexm_flash_programmed_bytes += n;
    return 0;
}

/* A fixed draw: the measurement's runs are reproducible (the real device's TRNG is drawn once per flash life). */
uint32_t cortexm_random32(void *ctx)
{
    (void)ctx;
    return 0x2545F491u;
}

void cortexm_return(void)
{
    for (;;) {
    }
}
