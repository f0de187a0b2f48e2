/* pyformat.h: the number formatting of Python's f-strings that the sensor's refusal texts use, so the C core's NAK
 * texts are byte-identical to the reference model's (onboard.banks, onboard.params, onboard.prior raise them).
 * No Python module of this name: it is the C side of `f"{x!r}"`, `f"{x:.3g}"`, `f"{x:.6g}"`, `f"{x:.0f}"`,
 * `f"{x:.0%}"`, `f"{n}"` and `f"{n:08x}"`.
 *
 * Floats are converted exactly: the binary value m 2^e is expanded to all its decimal digits (at most 770), then
 * rounded half-to-even, as CPython's dtoa does; repr is the shortest digit string that reads back to the same double
 * (round-half-even reading), the nearer of the two candidates when both do. Bounded work (no recursion, fixed
 * buffers), no I/O, no libc formatting. A text longer than PYFORMAT_TEXT_MAX is cut there (the texts are ASCII, so
 * this is protocol.messages.nak_text_bytes's cut). */
#ifndef PYFORMAT_H
#define PYFORMAT_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* protocol.messages.NAK_TEXT_MAX */
#define PYFORMAT_TEXT_MAX 120u

typedef struct {
    char buf[PYFORMAT_TEXT_MAX];
    uint32_t len;
} pyformat_text_t;

void pyformat_init(pyformat_text_t *t);
void pyformat_str(pyformat_text_t *t, const char *s);    /* a NUL-terminated ASCII string */
void pyformat_u64(pyformat_text_t *t, uint64_t v);        /* f"{n}" */
void pyformat_i64(pyformat_text_t *t, int64_t v);         /* f"{n}" */
void pyformat_hex08(pyformat_text_t *t, uint32_t v);      /* f"{n:08x}" */
void pyformat_repr(pyformat_text_t *t, double x);         /* f"{x!r}" (repr of a float) */
void pyformat_g(pyformat_text_t *t, double x, uint32_t p); /* f"{x:.{p}g}", p >= 1 */
void pyformat_f0(pyformat_text_t *t, double x);           /* f"{x:.0f}" */
void pyformat_percent0(pyformat_text_t *t, double x);     /* f"{x:.0%}" */

#ifdef __cplusplus
}
#endif
#endif /* PYFORMAT_H */
