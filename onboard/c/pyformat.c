/* pyformat.c: Python's float formatting in C for the refusal texts (pyformat.h). */
#include "pyformat.h"

#include <string.h>

/* 2^54 * 5^1076 has 770 decimal digits: the longest exact expansion of a double or of a midpoint between two. */
#define DEC_MAX_DIGITS 800
/* 5^13 and 2^28: the largest powers multiplied into the digits at once (digit * factor + carry < 2^64). */
#define POW5_CHUNK 1220703125u
#define POW5_CHUNK_EXP 13
#define POW2_CHUNK_EXP 28

/* A positive decimal 0.d[0]d[1]...d[n-1] x 10^dp, d[0] != 0, d[n-1] != 0 (n = 0: zero). */
typedef struct {
    uint8_t d[DEC_MAX_DIGITS];
    int32_t n;
    int32_t dp;
} dec_t;

void pyformat_init(pyformat_text_t *t) { t->len = 0u; }

static void put_char(pyformat_text_t *t, char c)
{
    if (t->len < PYFORMAT_TEXT_MAX) {
        t->buf[t->len] = c;
        t->len += 1u;
    }
}

void pyformat_str(pyformat_text_t *t, const char *s)
{
    while (*s != '\0') {
        put_char(t, *s);
        ++s;
    }
}

void pyformat_u64(pyformat_text_t *t, uint64_t v)
{
    char tmp[20];
    int32_t k = 0;
    do {
        tmp[k] = (char)('0' + (int)(v % 10u));
        v /= 10u;
        ++k;
    } while (v != 0u);
    while (k > 0) {
        --k;
        put_char(t, tmp[k]);
    }
}

void pyformat_i64(pyformat_text_t *t, int64_t v)
{
    if (v < 0) {
        put_char(t, '-');
        pyformat_u64(t, (uint64_t)(-(v + 1)) + 1u);
    } else {
        pyformat_u64(t, (uint64_t)v);
    }
}

void pyformat_hex08(pyformat_text_t *t, uint32_t v)
{
    static const char hex[] = "0123456789abcdef";
    int32_t shift;
    for (shift = 28; shift >= 0; shift -= 4) {
        put_char(t, hex[(v >> (uint32_t)shift) & 0xFu]);
    }
}

/* ------------------------------------------------------------------------------------------ exact expansion */
static uint64_t double_bits(double x)
{
    uint64_t b;
    memcpy(&b, &x, sizeof b);
    return b;
}

/* digits (least significant first) times factor, in place */
static void mul_small(uint8_t *w, int32_t *len, uint64_t factor)
{
    uint64_t carry = 0u;
    int32_t i;
    for (i = 0; i < *len; ++i) {
        uint64_t v = (uint64_t)w[i] * factor + carry;
        w[i] = (uint8_t)(v % 10u);
        carry = v / 10u;
    }
    while (carry != 0u && *len < DEC_MAX_DIGITS) {
        w[*len] = (uint8_t)(carry % 10u);
        carry /= 10u;
        *len += 1;
    }
}

/* the exact decimal of m 2^e2 (m > 0) */
static void expand(uint64_t m, int32_t e2, dec_t *out)
{
    uint8_t *w = out->d; /* the digits least significant first, reversed at the end: no second buffer */
    int32_t len = 0;
    int32_t i;
    int32_t k;
    while (m != 0u) {
        w[len] = (uint8_t)(m % 10u);
        m /= 10u;
        ++len;
    }
    if (e2 >= 0) {
        k = e2;
        while (k > 0) {
            int32_t step = k < POW2_CHUNK_EXP ? k : POW2_CHUNK_EXP;
            mul_small(w, &len, (uint64_t)1u << (uint32_t)step);
            k -= step;
        }
        out->dp = len;
    } else {
        k = -e2;
        while (k > 0) {
            int32_t step = k < POW5_CHUNK_EXP ? k : POW5_CHUNK_EXP;
            uint64_t f = 1u;
            int32_t j;
            for (j = 0; j < step; ++j) {
                f *= 5u;
            }
            mul_small(w, &len, f);
            k -= step;
        }
        out->dp = len + e2; /* divided by 10^-e2 */
    }
    out->n = len;
    for (i = 0; i < len / 2; ++i) {
        const uint8_t low = w[i];
        w[i] = w[len - 1 - i];
        w[len - 1 - i] = low;
    }
    while (out->n > 0 && out->d[out->n - 1] == 0u) {
        out->n -= 1;
    }
}

/* |x| = m 2^e2 with m an integer of at most 53 bits, e2 >= -1074 (x finite, nonzero) */
static void decompose(double x, uint64_t *m, int32_t *e2)
{
    uint64_t b = double_bits(x);
    uint64_t frac = b & (((uint64_t)1u << 52u) - 1u);
    int32_t be = (int32_t)((b >> 52u) & 0x7FFu);
    if (be == 0) {
        *m = frac;
        *e2 = -1074;
    } else {
        *m = frac | ((uint64_t)1u << 52u);
        *e2 = be - 1075;
    }
}

static int32_t dec_cmp(const dec_t *a, const dec_t *b)
{
    int32_t i;
    int32_t n;
    if (a->n == 0 || b->n == 0) {
        return (a->n != 0) - (b->n != 0);
    }
    if (a->dp != b->dp) {
        return a->dp > b->dp ? 1 : -1;
    }
    n = a->n > b->n ? a->n : b->n;
    for (i = 0; i < n; ++i) {
        int32_t da = i < a->n ? (int32_t)a->d[i] : 0;
        int32_t db = i < b->n ? (int32_t)b->d[i] : 0;
        if (da != db) {
            return da > db ? 1 : -1;
        }
    }
    return 0;
}

static void dec_trim(dec_t *x)
{
    while (x->n > 0 && x->d[x->n - 1] == 0u) {
        x->n -= 1;
    }
}

/* x cut to its first `keep` digits (keep may be <= 0 or >= n), plus one unit in the last kept place when up */
static void dec_cut(const dec_t *x, int32_t keep, int up, dec_t *out)
{
    int32_t i;
    out->dp = x->dp;
    if (keep <= 0) {
        out->n = 0;
        if (up) { /* one unit at position keep: 10^(dp - keep) */
            out->d[0] = 1u;
            out->n = 1;
            out->dp = x->dp - keep + 1;
        }
        return;
    }
    out->n = keep < x->n ? keep : x->n;
    for (i = 0; i < out->n; ++i) {
        out->d[i] = x->d[i];
    }
    for (i = out->n; i < keep; ++i) {
        out->d[i] = 0u;
    }
    out->n = keep;
    if (up) {
        i = keep - 1;
        while (i >= 0 && out->d[i] == 9u) {
            out->d[i] = 0u;
            --i;
        }
        if (i < 0) {
            out->d[0] = 1u;
            out->n = 1;
            out->dp += 1;
        } else {
            out->d[i] = (uint8_t)(out->d[i] + 1u);
        }
    }
    dec_trim(out);
}

/* round x half-to-even keeping `keep` digits: whether to round up */
static int round_up(const dec_t *x, int32_t keep)
{
    uint8_t next;
    int last_odd;
    if (keep >= x->n || keep < 0) {
        return 0;
    }
    next = x->d[keep];
    if (next != 5u) {
        return next > 5u;
    }
    if (x->n > keep + 1) {
        return 1; /* the digits after the 5 are not all zero (d[n-1] != 0) */
    }
    last_odd = keep > 0 ? (x->d[keep - 1] & 1u) != 0u : 0;
    return last_odd;
}

static void dec_round(const dec_t *x, int32_t keep, dec_t *out) { dec_cut(x, keep, round_up(x, keep), out); }

/* ------------------------------------------------------------------------------------------------ output */
static int put_special(pyformat_text_t *t, double x)
{
    uint64_t b = double_bits(x);
    if (((b >> 52u) & 0x7FFu) != 0x7FFu) {
        return 0;
    }
    if ((b & (((uint64_t)1u << 52u) - 1u)) != 0u) {
        pyformat_str(t, "nan");
    } else {
        pyformat_str(t, (b >> 63u) != 0u ? "-inf" : "inf");
    }
    return 1;
}

static void put_exponent(pyformat_text_t *t, int32_t e)
{
    put_char(t, 'e');
    put_char(t, e < 0 ? '-' : '+');
    if (e < 0) {
        e = -e;
    }
    if (e < 10) {
        put_char(t, '0');
    }
    pyformat_u64(t, (uint64_t)e);
}

/* the digits of x in fixed notation (no trailing zeros; the point and ".0" as asked) */
static void put_fixed(pyformat_text_t *t, const dec_t *x, int add_dot_zero)
{
    int32_t i;
    if (x->dp <= 0) {
        put_char(t, '0');
    } else {
        for (i = 0; i < x->dp; ++i) {
            put_char(t, (char)('0' + (i < x->n ? x->d[i] : 0)));
        }
    }
    if (x->n > x->dp) {
        put_char(t, '.');
        for (i = x->dp; i < 0; ++i) {
            put_char(t, '0');
        }
        for (i = x->dp > 0 ? x->dp : 0; i < x->n; ++i) {
            put_char(t, (char)('0' + x->d[i]));
        }
    } else if (add_dot_zero) {
        pyformat_str(t, ".0");
    }
}

static void put_sci(pyformat_text_t *t, const dec_t *x)
{
    int32_t i;
    put_char(t, (char)('0' + x->d[0]));
    if (x->n > 1) {
        put_char(t, '.');
        for (i = 1; i < x->n; ++i) {
            put_char(t, (char)('0' + x->d[i]));
        }
    }
    put_exponent(t, x->dp - 1);
}

static int is_negative(double x) { return (double_bits(x) >> 63u) != 0u; }

void pyformat_g(pyformat_text_t *t, double x, uint32_t p)
{
    dec_t exact;
    dec_t r;
    uint64_t m;
    int32_t e2;
    int32_t exp10;
    if (put_special(t, x)) {
        return;
    }
    if (is_negative(x)) {
        put_char(t, '-');
    }
    if (x == 0.0) {
        put_char(t, '0');
        return;
    }
    if (p == 0u) {
        p = 1u;
    }
    decompose(x, &m, &e2);
    expand(m, e2, &exact);
    dec_round(&exact, (int32_t)p, &r);
    exp10 = r.dp - 1;
    if (exp10 >= -4 && exp10 < (int32_t)p) {
        put_fixed(t, &r, 0);
    } else {
        put_sci(t, &r);
    }
}

void pyformat_f0(pyformat_text_t *t, double x)
{
    dec_t exact;
    dec_t r;
    uint64_t m;
    int32_t e2;
    if (put_special(t, x)) {
        return;
    }
    if (is_negative(x)) {
        put_char(t, '-');
    }
    if (x == 0.0) {
        put_char(t, '0');
        return;
    }
    decompose(x, &m, &e2);
    expand(m, e2, &exact);
    dec_round(&exact, exact.dp, &r);
    if (r.n == 0) {
        put_char(t, '0');
    } else {
        put_fixed(t, &r, 0);
    }
}

void pyformat_percent0(pyformat_text_t *t, double x)
{
    pyformat_f0(t, x * 100.0);
    put_char(t, '%');
}

/* does the decimal c read back (round-half-even) as the double m 2^e2? */
static int reads_back(const dec_t *c, const dec_t *lower, const dec_t *upper, int even)
{
    int32_t lo = dec_cmp(c, lower);
    int32_t hi = dec_cmp(c, upper);
    if (lo > 0 && hi < 0) {
        return 1;
    }
    return even && (lo == 0 || hi == 0);
}

void pyformat_repr(pyformat_text_t *t, double x)
{
    dec_t exact;
    dec_t lower;
    dec_t upper;
    dec_t cand; /* one candidate at a time (the shorter ones cut down or up), then the chosen one: 0.8 kB of stack */
    const dec_t *best = &exact;
    uint64_t m;
    int32_t e2;
    int32_t p;
    int32_t keep = 0;
    int up = 0;
    int even;
    if (put_special(t, x)) {
        return;
    }
    if (is_negative(x)) {
        put_char(t, '-');
    }
    if (x == 0.0) {
        pyformat_str(t, "0.0");
        return;
    }
    decompose(x, &m, &e2);
    even = (m & 1u) == 0u;
    expand(m, e2, &exact);
    expand(2u * m + 1u, e2 - 1, &upper);
    if (m == ((uint64_t)1u << 52u) && e2 > -1074) {
        expand(4u * m - 1u, e2 - 2, &lower); /* a power of two: the double below is half as far */
    } else {
        expand(2u * m - 1u, e2 - 1, &lower);
    }
    for (p = 1; p <= 17 && p < exact.n; ++p) {
        int in_down;
        int in_up;
        dec_cut(&exact, p, 0, &cand);
        in_down = reads_back(&cand, &lower, &upper, even);
        dec_cut(&exact, p, 1, &cand);
        in_up = reads_back(&cand, &lower, &upper, even);
        if (in_down || in_up) { /* both read back: the nearer, as rounding the exact digits chooses */
            keep = p;
            up = in_down && in_up ? round_up(&exact, p) : in_up;
            break;
        }
    }
    if (keep > 0) {
        dec_cut(&exact, keep, up, &cand);
        best = &cand;
    }
    if (best->dp <= -4 || best->dp > 16) {
        put_sci(t, best);
    } else {
        put_fixed(t, best, 1);
    }
}
