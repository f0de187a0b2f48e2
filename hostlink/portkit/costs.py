"""Cost table of the onboard functions a port needs: arithmetic operations and working memory per frame at N stars,
in float32 and in fixed point, so a firmware engineer can budget the sensor on a given microcontroller
(``hostlink costs``; docs/port-kit.md).

Where the counts come from:

* Counted formulas, written from the code line by line (each function below names the lines it counts):
  :func:`pixel_to_direction_ops` (``onboard.camera.pixels_to_unit``), :func:`pixel_to_direction_fixed_ops`
  (``onboard.fixedpoint.pixels_to_unit_q30``), :func:`interstar_residual_ops` (``onboard.interstar
  .difference_residuals`` and its Q61 twin), :func:`interstar_jacobian_ops` (``difference_jacobian``),
  :func:`bierman_update_ops` (``onboard.ud.bierman_update``), :func:`refraction_fixed_ops` (``onboard.refraction
  .topocentric_observed_q30``) and :func:`apparent_place_fixed_ops` (``onboard.apparent
  .apparent_place_vectors_q30``); the fixed-point ones are built from the costs of the integer primitives of
  ``onboard.fixedpoint`` (``_ROUND``, ``_DIV_ROUND``, ``_BIT_LENGTH``, :func:`_rsqrt_q30_ops`, ...).
  ``tests/test_portkit_costs.py`` holds each against an instrumented run of the code (:func:`count_operations`, a
  numpy array subclass that counts every element of every ufunc it goes through). :func:`bank_record_verify_ops`
  counts the CRC loop of the generated C (the test pins that line).
* Measured: functions whose structure is long (float32 camera Jacobians, refraction, apparent place, the fixed
  point's once-per-frame instant quantities, attitude) are counted
  by running the reference code on N stars through :func:`count_operations`; the count is exact for the code as
  written (LAPACK calls inside ``np.linalg``, i.e. the attitude's one 3 x 3 SVD and 3 x 3 solve, are not seen and
  are listed as a constant).
* The estimator's whole frame is ``onboard.recursive.update_cost_flops`` (the sensor's own budget model,
  ``onboard.firmware.EstimatorBudget``), reused, not restated.

Operations are counted as the reference code performs them (numpy on whole arrays): a C port that exploits the unit
upper-triangular U in the U-D update, or replaces a division by 2 with a multiplication, does less. ``add`` counts
additions and subtractions, ``cmp`` comparisons and selections, ``shift`` integer shifts, masks and XORs,
``trig`` sin/cos/tan/atan2/asin. Memory is the working buffers one call needs (inputs, outputs, intermediates the
code keeps), in bytes: float32 4, float64 and int64 8 (fixed point's Q30/Q61 values), int32 4 (Q10 centroids).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from onboard.banks import BANK_RECORD_BYTES
from onboard.recursive import RecursiveConfig, update_cost_flops

#: Categories of :class:`Ops`, in table order.
CATEGORIES: tuple[str, ...] = ("mul", "add", "div", "sqrt", "trig", "shift", "cmp")

_UFUNC_CATEGORY = {
    "multiply": "mul",
    "square": "mul",
    "add": "add",
    "subtract": "add",
    "true_divide": "div",
    "divide": "div",
    "floor_divide": "div",
    "reciprocal": "div",
    "remainder": "div",
    "sqrt": "sqrt",
    "sin": "trig",
    "cos": "trig",
    "tan": "trig",
    "arctan2": "trig",
    "arcsin": "trig",
    "arccos": "trig",
    "arctan": "trig",
    "right_shift": "shift",
    "left_shift": "shift",
    "bitwise_and": "shift",
    "bitwise_or": "shift",
    "bitwise_xor": "shift",
    "maximum": "cmp",
    "minimum": "cmp",
    "greater": "cmp",
    "greater_equal": "cmp",
    "less": "cmp",
    "less_equal": "cmp",
    "equal": "cmp",
    "not_equal": "cmp",
    "absolute": "cmp",
}


@dataclass(frozen=True)
class Ops:
    """Operation counts of one call."""

    mul: int = 0
    add: int = 0
    div: int = 0
    sqrt: int = 0
    trig: int = 0
    shift: int = 0
    cmp: int = 0

    @property
    def flops(self) -> int:
        """Arithmetic operations (mul + add + div + sqrt + trig; comparisons and shifts excluded)."""
        return self.mul + self.add + self.div + self.sqrt + self.trig

    def __add__(self, other: Ops) -> Ops:
        return Ops(**{c: getattr(self, c) + getattr(other, c) for c in CATEGORIES})

    def scaled(self, k: int) -> Ops:
        return Ops(**{c: k * getattr(self, c) for c in CATEGORIES})

    def as_dict(self) -> dict[str, int]:
        return {c: getattr(self, c) for c in CATEGORIES}


# ------------------------------------------------------------------------------------------ instrumented counts
class _Counted(np.ndarray):
    """An ndarray that adds the element count of every ufunc it takes part in to :data:`_Counted.tally`; numpy
    functions on it (stack, where, einsum, dot, cross, ...) return instrumented arrays again, and those that do
    arithmetic outside the ufuncs (einsum, dot, cross) are counted by their shapes."""

    tally: Counter = Counter()

    def __array_ufunc__(self, ufunc, method, *inputs, out=None, **kwargs):
        args = [x.view(np.ndarray) if isinstance(x, _Counted) else x for x in inputs]
        if out is not None:
            kwargs["out"] = tuple(o.view(np.ndarray) if isinstance(o, _Counted) else o for o in out)
        result = getattr(ufunc, method)(*args, **kwargs)
        _Counted.tally.update(_ufunc_ops(ufunc, method, args, result, kwargs.get("axis", 0)))
        if out is not None:
            return out[0] if len(out) == 1 else out
        if isinstance(result, tuple):
            return tuple(_wrap(r) for r in result)
        return _wrap(result)

    def __array_function__(self, func, types, args, kwargs):
        plain = [a.view(np.ndarray) if isinstance(a, _Counted) else a for a in args]
        if func in (np.einsum, np.dot, np.cross):
            result = func(*plain, **kwargs)
            _Counted.tally.update(_contraction_ops(func, plain, result))
            return _wrap(result)
        result = super().__array_function__(
            func, tuple(t for t in types if t is not _Counted) or (np.ndarray,), args, kwargs
        )
        if isinstance(result, tuple):
            return tuple(_wrap(r) for r in result)
        return _wrap(result)


def _wrap(x):
    """Results of instrumented work stay instrumented (a 0-d result too, which numpy would make a scalar)."""
    if isinstance(x, np.generic):
        return np.asarray(x).view(_Counted)
    return x.view(_Counted) if isinstance(x, np.ndarray) and not isinstance(x, _Counted) else x


def _contraction_ops(func, args, result) -> dict[str, int]:
    """Multiplications and additions of einsum (two operands), dot and cross, from their shapes."""
    n_out = max(int(np.size(result)), 1)
    if func is np.cross:
        return {"mul": 2 * n_out, "add": n_out}
    if func is np.dot:
        a = np.asarray(args[0])
        k = a.shape[-1] if a.ndim else 1
        return {"mul": n_out * k, "add": n_out * (k - 1)}
    subscripts = args[0].replace(" ", "")
    inputs, output = subscripts.split("->")
    sizes: dict[str, int] = {}
    for letters, operand in zip(inputs.split(","), args[1:], strict=False):
        ellipsis_dims = np.ndim(operand) - len(letters.replace("...", ""))
        letters = letters.replace("...", "".join(chr(0x100 + d) for d in range(ellipsis_dims)))
        sizes.update(zip(letters, np.shape(operand), strict=True))
    total = int(np.prod(list(sizes.values()), dtype=np.int64))
    return {"mul": total * (len(inputs.split(",")) - 1), "add": total - n_out}


def _ufunc_ops(ufunc, method: str, args, result, axis=0) -> dict[str, int]:
    if ufunc is np.matmul:
        a = np.asarray(args[0])
        k = a.shape[-1]
        n_out = int(np.size(result))
        return {"mul": n_out * k, "add": n_out * (k - 1)}
    category = _UFUNC_CATEGORY.get(ufunc.__name__)
    if category is None:
        return {}
    if method == "__call__":
        return {category: int(np.size(result))}
    if method in ("reduce", "accumulate"):
        a = np.asarray(args[0])
        if method == "accumulate" or a.ndim == 0:  # one operation per output but the first along the axis
            n_axis = a.shape[axis if axis is not None else 0] if a.ndim else 1
            return {category: int(np.size(result)) - int(np.size(result)) // max(n_axis, 1)}
        return {category: int(a.size - np.size(result))}
    return {}


#: numpy constructors that take no array (so no dispatch): instrumented while counting, so buffers a function
#: allocates inside itself count too.
_CONSTRUCTORS = ("zeros", "empty", "ones", "eye", "full")
#: numpy converters that would turn an instrumented input into a plain array (``np.asarray`` does not dispatch):
#: while counting, an instrumented input stays instrumented through them (``r = np.asarray(r)`` at the top of a
#: function would otherwise hide all its work).
_CONVERTERS = ("asarray",)


def counted(array: np.ndarray) -> np.ndarray:
    """``array`` as an instrumented array (same data and dtype): every ufunc it meets is counted."""
    return np.asarray(array).view(_Counted)


def count_operations(fn: Callable, *args, **kwargs) -> Ops:
    """Operations one call ``fn(*args, **kwargs)`` performs on arrays (pass the inputs through :func:`counted`):
    every element of every ufunc, matmul/dot/einsum/cross as their multiplications and additions, reductions as
    their additions. Buffers the function allocates (np.zeros, np.empty, ...) are instrumented for the duration of
    the call, and ``np.asarray`` of an instrumented input stays instrumented (the numpy functions are wrapped, then
    restored). Not seen: work on Python or numpy scalars
    (per-call constants) and LAPACK calls (np.linalg)."""
    saved = {name: getattr(np, name) for name in _CONSTRUCTORS + _CONVERTERS}

    def instrumented(constructor):
        return lambda *a, **k: constructor(*a, **k).view(_Counted)

    def keeps_instrumented(converter):
        def convert(a, *rest, **k):
            result = converter(a, *rest, **k)
            return result.view(_Counted) if isinstance(a, _Counted) else result

        return convert

    _Counted.tally = Counter()
    try:
        for name in _CONSTRUCTORS:
            setattr(np, name, instrumented(saved[name]))
        for name in _CONVERTERS:
            setattr(np, name, keeps_instrumented(saved[name]))
        fn(*args, **kwargs)
    finally:
        for name, original in saved.items():
            setattr(np, name, original)
    tally = _Counted.tally
    return Ops(**{c: int(tally.get(c, 0)) for c in CATEGORIES})


# ------------------------------------------------------------------------------------------ counted formulas
def pixel_to_direction_ops(n_stars: int) -> Ops:
    """``onboard.camera.pixels_to_unit`` for N stars. Per star: u, v = x - x0, y - y0 (2 add); distortion_px:
    r2 = u u + v v (2 mul, 1 add), radial = r2 (k1 + r2 (k2 + r2 k3)) (3 mul, 2 add), dx and dy each 7 mul and
    3 add; u - dx, v - dy (2 add); offsets_to_unit: u'^2 + v'^2 + F^2 (2 mul, 2 add), sqrt (1), (u', v', F) over
    it (3 div). The 4 additions g1..g4 of the coefficients and F^2 are per call."""
    n = int(n_stars)
    return Ops(mul=21 * n, add=15 * n, div=3 * n, sqrt=n)


# Integer primitives of onboard.fixedpoint, per value (the fixed-point formulas below are built from them).
#: ``rshift_round(a, n)`` by a constant n: a + 2^(n-1) (the power is per call), then >>.
_ROUND = Ops(add=1, shift=1)
#: ``rshift_round(a, k)`` by a per-value k: also k - 1 and 1 << (k - 1).
_ROUND_BY_VALUE = Ops(add=2, shift=2)
#: ``div_round(a, b)`` by a per-value b > 0: b >> 1, a + that, the floor division.
_DIV_ROUND = Ops(add=1, shift=1, div=1)
#: ``div_round(a, d)`` by a constant d (d >> 1 is per call).
_DIV_ROUND_BY_CONSTANT = Ops(add=1, div=1)
#: ``bit_length``: 6 steps of (y >> k) > 0, n + where(big, k, 0), where(big, y >> k, y); then n + (y > 0).
_BIT_LENGTH = Ops(add=6 + 1, shift=2 * 6, cmp=6 + 1)


def _rsqrt_q30_ops() -> Ops:
    """``onboard.fixedpoint.rsqrt_q30`` per value: the bit length; sh = length - Q - 1 (2 add); made odd
    sh + ((sh + 1) & 1) (2 add, 1 mask); a = n2 rounded by sh (per value); the table index (a >> 26) - first
    (1 shift, 1 add); per Newton step (RSQRT_ITERATIONS): t1 = a y and t2 = t1 y rounded (2 mul, 2 roundings),
    3 2^30 - t2 (1 add), y times it rounded (1 mul, 1 rounding); k = (Q + 1 + sh) >> 1 (1 add, 1 shift)."""
    from onboard.fixedpoint import RSQRT_ITERATIONS

    newton = (Ops(mul=3, add=1) + _ROUND.scaled(3)).scaled(RSQRT_ITERATIONS)
    return _BIT_LENGTH + Ops(add=2 + 2 + 1 + 1, shift=1 + 1 + 1) + _ROUND_BY_VALUE + newton


def _isqrt_ops() -> Ops:
    """``onboard.fixedpoint.isqrt`` per value: the bit length, x0 = max(1 << ((bits + 1) >> 1), 1) (1 add,
    2 shift, 1 cmp); per Newton step (ISQRT_ITERATIONS): min(x, max((x + n // x) >> 1, 1)) (1 div, 1 add,
    1 shift, 2 cmp); the final where(n > 0, x, 0) (1 cmp)."""
    from onboard.fixedpoint import ISQRT_ITERATIONS

    step = Ops(div=1, add=1, shift=1, cmp=2)
    return _BIT_LENGTH + Ops(add=1, shift=2, cmp=1) + step.scaled(ISQRT_ITERATIONS) + Ops(cmp=1)


def _normalise_q30_ops() -> Ops:
    """``onboard.fixedpoint.normalise_q30`` per vector: |w|^2 (3 mul, 2 add), the reciprocal square root, w y
    (3 mul) rounded by the per-vector k broadcast over the 3 components (k - 1 and its power once: 1 add, 1 shift;
    then 3 add, 3 shift)."""
    return Ops(mul=3 + 3, add=2 + 1 + 3, shift=1 + 3) + _rsqrt_q30_ops()


def pixel_to_direction_fixed_ops(n_stars: int) -> Ops:
    """``onboard.fixedpoint.pixels_to_unit_q30`` for N stars, int64 arithmetic. A rounding shift ``rshift_round``
    by a constant is 1 add + 1 shift; by a per-star amount 2 add + 2 shift (it forms 2^(n-1) too). Per star:

    ideal_offsets_q30: u, v (2 shift, 2 add); the range check (4 cmp); uu vv uv (3 mul, 3 roundings); r2 (1 add);
    r4 (1 mul, 1 rounding); r6 (1 mul, 2 roundings); radial = 3 coefficient terms (3 mul, 3 roundings) + 2 add;
    ru rv (2 mul, 2 roundings); uv2 (1 add); dx and dy each: 3uu+vv (1 mul, 1 add), 3 coefficient terms (3 mul,
    3 roundings), 3 add; u - dx, v - dy (2 add). Subtotal 18 mul, 33 add, 19 shift, 4 cmp.

    offsets_to_unit_q30: wu wv (2 roundings); |w|^2 (2 mul, 2 add: F^2 is per call); rsqrt_q30: the bit length by
    binary search (6 steps of 2 shift, 1 cmp, 1 add; then 1 cmp, 1 add), sh (2 add), made odd (2 add, 1 mask),
    a = n2 rounded by sh (1 per-star rounding), the table index (1 shift, 1 add), 3 Newton steps (3 mul, 1 add,
    3 roundings each), k (1 add, 1 shift); b = w y rounded by k (3 mul, 3 per-star roundings).
    Subtotal 14 mul, 37 add, 34 shift, 7 cmp."""
    n = int(n_stars)
    ideal = Ops(mul=18, add=33, shift=19, cmp=4)
    to_unit = Ops(mul=2 + 3, add=2 + 2 + 6, shift=2 + 6) + _rsqrt_q30_ops()
    return (ideal + to_unit).scaled(n)


def interstar_residual_ops(n_pairs: int, fixed: bool = False) -> Ops:
    """``onboard.interstar.difference_residuals`` for P pairs: b_i - b_j and r_i - r_j (6 add), the two squared
    norms (6 mul, 4 add), their difference (1 add) and the halving (1 div; a port multiplies by 0.5).
    The Q61 twin ``difference_residuals_q61`` is the same without the halving (it is in the format)."""
    p = int(n_pairs)
    return Ops(mul=6 * p, add=11 * p, div=0 if fixed else p)


def interstar_jacobian_ops(n_pairs: int, n_states: int) -> Ops:
    """``onboard.interstar.difference_jacobian`` for P pairs and K states: b_i - b_j (3 add), J_i - J_j (3K add),
    the contraction -(b_i - b_j)^T (J_i - J_j) (3K mul, 2K add)."""
    p, k = int(n_pairs), int(n_states)
    return Ops(mul=3 * k * p, add=(3 + 5 * k) * p)


def _cos_sin_q30_ops() -> Ops:
    """``onboard.refraction._cos_sin_q30`` per value: R to Q30, R^2, R^4 (2 mul, 3 roundings); cos R = 2^30 -
    R^2 / 2 + R^4 / 24 (1 rounding, 2 add, a division by a constant); sin R = R - R^3 / 6 (1 mul, 1 rounding,
    1 add, a division by a constant)."""
    return Ops(mul=3, add=2 + 1) + _ROUND.scaled(5) + _DIV_ROUND_BY_CONSTANT.scaled(2)


def refraction_fixed_ops(n_stars: int) -> Ops:
    """``onboard.refraction.topocentric_observed_q30`` (diurnal aberration, then refraction by addition) for N
    directions, int64 arithmetic. Per direction:

    aberration: r . beta (3 mul, 2 add) rounded; r << 18 (3 shift), + beta (3 add), (r.beta) r (3 mul) rounded,
    the difference (3 add), rounded to Q30 (3); 6 mul, 15 add, 10 shift.
    geometry: cos z = r . U (3 mul, 2 add) rounded; t = U - cos z r (3 mul, 3 roundings, 3 add); |t|^2 (3 mul,
    2 add) and its integer square root; the ratio sin R / sin z = where(sin z > 0, div_round(sin R << 30,
    max(sin z, 1)), 0) (2 cmp, 1 shift, 1 division); r cos R + t ratio (6 mul, 3 add) rounded (3).
    R: ``refraction_from_true_zenith_q36``, TRUE_ZENITH_NEWTON_STEPS steps of: cos R, sin R; cos(z - R) (2 mul,
    1 add, 1 rounding, 1 cmp for the clamp) and sin(z - R) (2 mul, 1 add, 1 rounding); tan = div_round(s << 24,
    c) (1 shift, 1 division); tan^2, B tan^2 (2 mul, 2 roundings); k = A + B tan^2 (1 add); f = k tan (1 mul,
    2 roundings); g = R - f (1 add); cos^2 (1 mul, 1 rounding); the derivative 2^30 + div_round((A + 3 B tan^2)
    << 4, cos^2) (1 mul, 2 add, 1 shift, 1 division); R - div_round(g << 30, derivative) (1 shift, 1 division,
    1 add). Then cos R, sin R of the result once more."""
    from onboard.refraction import TRUE_ZENITH_NEWTON_STEPS

    n = int(n_stars)
    aberration = Ops(mul=6, add=2 + 3 + 3, shift=3) + _ROUND.scaled(1 + 3 + 3)
    geometry = (
        Ops(mul=3 + 3 + 3 + 6, add=2 + 3 + 2 + 3, shift=1, cmp=2)
        + _ROUND.scaled(1 + 3 + 3)
        + _isqrt_ops()
        + _DIV_ROUND
        + _cos_sin_q30_ops()
    )
    step = (
        _cos_sin_q30_ops()
        + Ops(mul=2 + 2 + 2 + 1 + 1 + 1, add=1 + 1 + 1 + 1 + 2 + 1, shift=1 + 1 + 1, cmp=1)
        + _ROUND.scaled(1 + 1 + 2 + 2 + 1)
        + _DIV_ROUND.scaled(3)
    )
    return (aberration + geometry + step.scaled(TRUE_ZENITH_NEWTON_STEPS)).scaled(n)


def apparent_place_fixed_ops(n_stars: int) -> Ops:
    """``onboard.apparent.apparent_place_vectors_q30`` for N stars at one instant, int64 arithmetic (the instant's
    quantities, ``apparent.fixed_instant``, are inputs: see :func:`apparent_instant_ops`). Per star:

    space motion c1 = years pm (3 mul, 3 roundings) - parallax E_b (3 mul, 3 roundings, 3 add); p = r0 + c1 in
    Q30 (3 shift, 3 add, 3 roundings); p . e (3 mul, 2 add) rounded; max(2^30 + p.e, clamp) (1 add, 1 cmp);
    q = div_round(k, 1 + p.e) (a per-star division); c2 = c1 + q (e - (p.e) p) (6 mul, 6 roundings, 6 add);
    p = normalise(r0 + c2) (3 shift, 3 add, 3 roundings, the normalisation); p . v (3 mul, 2 add) rounded;
    m = p.v - (p.v)^2 + v^2 / 2 (1 mul, 1 rounding, 2 add; v^2 is per call); the aberration change v - (p.v) v / 2
    - m p (6 mul, 6 roundings, 6 add); c3 = c2 + (ab << 4) (3 shift, 3 add); p = normalise(r0 + c3) (as before);
    p M^T (9 mul, 6 add) rounded (3)."""
    n = int(n_stars)
    to_q30 = Ops(shift=3, add=3) + _ROUND.scaled(3)  # r0 << 18 + change, rounded to Q30
    parts = (
        Ops(mul=3 + 3, add=3) + _ROUND.scaled(3 + 3),  # c1
        to_q30,
        Ops(mul=3, add=2 + 1, cmp=1) + _ROUND + _DIV_ROUND,  # p.e, 1 + p.e, q
        Ops(mul=6, add=6) + _ROUND.scaled(6),  # c2
        to_q30 + _normalise_q30_ops(),
        Ops(mul=3 + 1, add=2 + 2) + _ROUND.scaled(1 + 1),  # p.v, m
        Ops(mul=6, add=6) + _ROUND.scaled(6),  # aberration change
        Ops(shift=3, add=3),  # c3
        to_q30 + _normalise_q30_ops(),
        Ops(mul=9, add=6) + _ROUND.scaled(3),  # rotation to TOD
    )
    per_star = Ops()
    for part in parts:
        per_star = per_star + part
    return per_star.scaled(n)


#: The line of the generated C (``hostlink export-c``, st_protocol.c) that :func:`bank_record_verify_ops` counts.
CRC32_BYTE_STEP_C = "crc = st_crc32_table[(crc ^ p[i]) & 0xFFu] ^ (crc >> 8);"


def bank_record_verify_ops() -> Ops:
    """Verifying one bank record (``onboard.banks.decode_bank_record``; ``st_crc32`` of ``hostlink export-c``):
    the CRC-32 over the record's bytes before its CRC, one :data:`CRC32_BYTE_STEP_C` per byte (2 XOR, 1 mask,
    1 shift, and one look-up in the 1 KiB table), the final XOR, and two comparisons (magic, CRC). Not per frame:
    at boot for each bank, and once per upload."""
    body = BANK_RECORD_BYTES - 4
    return Ops(shift=4 * body + 1, cmp=2)


def bierman_update_ops(n_states: int) -> Ops:
    """``onboard.ud.bierman_update`` (one scalar measurement, K states) as written: f = h U (K^2 mul, K(K-1) add);
    v = d f, f v (2K mul); alpha = 1 + cumsum (K - 1 + K add); d *= alpha_prev (K mul), d /= alpha (K div);
    U v by columns (K^2 mul) and their cumulative sums (K(K-1) add); xi += b_K innovation / s (K mul, K add, 1 div);
    f /= alpha_prev (K div); the column update (K(K-1) mul, K(K-1) add); the innovation y - h . xi (K mul, K add).
    Total 6 K^2 + 7 K flops (the "about 6 K^2" of the module)."""
    k = int(n_states)
    mul = k * k + 2 * k + k + k * k + k + k * (k - 1) + k
    add = k * (k - 1) + (k - 1) + k + k * (k - 1) + k + k * (k - 1) + k
    return Ops(mul=mul, add=add, div=2 * k + 1)


# --------------------------------------------------------------------------------------------- measured counts
def _theta() -> np.ndarray:
    return np.array([5852.18, 500.0, 530.0, -2e-10, 3.5e-15, -1e-20, 2e-7, -1.5e-7, 1e-7, -5e-8], dtype=np.float32)


def _stars(n: int, dtype=np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(n)
    x = rng.uniform(0, 1023, n).astype(dtype)
    y = rng.uniform(0, 1023, n).astype(dtype)
    r = rng.normal(size=(n, 3))
    r[:, 2] = np.abs(r[:, 2]) + 8
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return x, y, r.astype(dtype)


def unit_vector_jacobian_ops(n_stars: int) -> Ops:
    """``onboard.camera.unit_vector_jacobians`` for N stars, counted by an instrumented run."""
    from onboard.camera import unit_vector_jacobians

    x, y, _ = _stars(n_stars)
    return count_operations(unit_vector_jacobians, counted(x), counted(y), counted(_theta()))


def refraction_ops(n_stars: int) -> Ops:
    """``onboard.refraction.refract_toward_zenith`` for N directions (atan model, 2 Newton steps), instrumented."""
    from onboard.refraction import refract_toward_zenith
    from onboard.site import Weather

    _, _, r = _stars(n_stars)
    zenith = np.array([0.0, 0.6, 0.8], dtype=np.float32)
    return count_operations(refract_toward_zenith, counted(r), counted(zenith), Weather(10.0, 1000.0, 0.5))


def apparent_place_ops(n_stars: int) -> Ops:
    """``onboard.apparent.apparent_place_vectors`` for N stars at one instant, instrumented; the per-instant part
    (Earth state, precession-nutation matrix) is included once."""
    from onboard.apparent import apparent_place_vectors
    from onboard.timescale import make_time

    _, _, r = _stars(n_stars)
    pm = np.full((n_stars, 3), 1e-8, dtype=np.float32)
    plx = np.full(n_stars, 10.0, dtype=np.float32)
    t = make_time(9497, 1 << 31)
    t = type(t)(counted(t.day), counted(t.frac))  # the per-instant part (Earth state, matrix) counts too
    return count_operations(apparent_place_vectors, counted(r), counted(pm), counted(plx), 1991.25, t)


def apparent_instant_ops() -> Ops:
    """``onboard.apparent.fixed_instant``, the once-per-frame quantities of the fixed-point apparent place (Earth
    state, years, deflection, velocity, GCRS -> TOD matrix), instrumented: soft float64 on a sensor without an FPU.
    Arithmetic on Python floats (a handful of scalar steps) is not seen."""
    from onboard.apparent import EPOCH_HIPPARCOS_JYEAR, fixed_instant
    from onboard.timescale import make_time

    t = make_time(9497, 1 << 31)
    return count_operations(fixed_instant, type(t)(counted(t.day), counted(t.frac)), EPOCH_HIPPARCOS_JYEAR)


def attitude_ops(n_stars: int) -> Ops:
    """``onboard.attitude.attitude_from_vectors`` for N stars, instrumented (plus one 3 x 3 SVD and two 3 x 3
    solves inside LAPACK, not counted)."""
    from onboard.attitude import attitude_from_vectors

    _, _, r = _stars(n_stars)
    b = r[:, [1, 0, 2]] * np.array([1, 1, 1], dtype=np.float32)
    return count_operations(attitude_from_vectors, counted(b), counted(r))


# ------------------------------------------------------------------------------------------------- the table
@dataclass(frozen=True)
class CostRow:
    """One line of the cost table: a function at N stars (P = 2N - 3 pairs, K states), its operations and working
    memory [bytes], in one precision."""

    function: str
    precision: str
    ops: Ops
    memory_bytes: int
    note: str = ""
    extra: dict = field(default_factory=dict)


#: Bytes of the words the memory column counts: float32, int64 (the Q formats' accumulators), int32 (Q10
#: centroids) and float64 (the once-per-instant apparent place).
_F32, _I64, _I32, _F64 = 4, 8, 4, 8


def cost_table(n_stars: int = 32, n_states: int = 10, config: RecursiveConfig | None = None) -> list[CostRow]:
    """The cost table at ``n_stars`` stars and ``n_states`` estimated parameters (docs/port-kit.md): the camera
    model, the estimator, the reference directions, then the bank check and the attitude."""
    n, k = int(n_stars), int(n_states)
    if n < 3:
        raise ValueError(f"the cost table needs at least 3 stars, got {n}")
    return [*_camera_rows(n), *_estimator_rows(n, k, config or RecursiveConfig()), *_reference_rows(n), *_other_rows(n)]


def _camera_rows(n: int) -> list[CostRow]:
    """Pixels to directions (float32 and the fixed-point front end) and the directions' Jacobians, for n stars."""
    return [
        CostRow(
            "pixel_to_direction",
            "float32",
            pixel_to_direction_ops(n),
            _F32 * (2 * n + 10 + 3 * n),
            "x, y, theta in; b (N, 3) out",
        ),
        CostRow(
            "pixel_to_direction",
            "fixed",
            pixel_to_direction_fixed_ops(n),
            _I32 * 2 * n + _I64 * (3 * n + 2 * n + 20),
            "Q10 centroids in; Q30 u', v' and b (N, 3) out; camera in block floating point",
        ),
        CostRow(
            "unit_vector_jacobians",
            "float32",
            unit_vector_jacobian_ops(n),
            _F32 * (3 * n + 30 * n + 6 * n + 9 * n + 30 * n + 20 * n),
            "b, db/dtheta (N, 3, 10), db/dxy (N, 3, 2) and the (N, 3, 3) projector; fixed-point sensors run this "
            "in float32 (soft float)",
        ),
    ]


def _estimator_rows(n: int, k: int, cfg: RecursiveConfig) -> list[CostRow]:
    """The interstar residuals and Jacobian, one Bierman update and the whole estimator frame, for n stars and k
    estimated parameters."""
    p = 2 * n - 3
    n_est = min(n, cfg.max_stars)  # the estimator uses at most max_stars stars of a frame
    p_est, linearisations = 2 * n_est - 3, cfg.max_iterations + 2
    return [
        CostRow("interstar_residual", "float32", interstar_residual_ops(p), _F32 * (6 * n + p), "P = 2N - 3 pairs"),
        CostRow(
            "interstar_residual", "fixed", interstar_residual_ops(p, fixed=True), _I64 * (6 * n + p), "Q30 in, Q61 out"
        ),
        CostRow(
            "interstar_jacobian",
            "float32",
            interstar_jacobian_ops(p, k),
            _F32 * (3 * n + 3 * n * k + p * k),
            "H (P, K)",
        ),
        CostRow(
            "bierman_update",
            "float32",
            bierman_update_ops(k),
            _F32 * (k * k + 2 * k + 4 * k + k * k),
            "one whitened pair; P of them per linearisation; fixed-point sensors: float32 soft float",
        ),
        CostRow(
            "estimator_frame",
            "float32",
            Ops(),
            _F32 * (5 * n + 30 * n + 6 * n + p + p * k + p * p + p * (k + 1) + k * k + 6 * k),
            "worst case of onboard.recursive.update (update_cost_flops): (max_iterations + 2) linearisations of "
            "P^3/3 + P^2 (K + 1) + 6 P K^2 + 40 N K flops",
            {"flops": update_cost_flops(n, k, cfg)},
        ),
        CostRow(
            "estimator_frame_front_end",
            "fixed",
            (pixel_to_direction_fixed_ops(n_est) + interstar_residual_ops(p_est, fixed=True)).scaled(linearisations),
            _I32 * 2 * n_est + _I64 * (3 * n_est + 3 * n_est + 2 * n_est + p_est),
            "a sensor without an FPU: the integer front end once per linearisation (max_iterations + 2), on top "
            "of the estimator_frame flops in float32 soft float (the front end replaces no float work: the "
            "Jacobians still need b)",
        ),
    ]


def _reference_rows(n: int) -> list[CostRow]:
    """Reference directions for n stars: refraction by addition, the apparent place and its per-instant part."""
    return [
        CostRow(
            "refraction_by_addition",
            "float32",
            refraction_ops(n),
            _F32 * (3 * n * 3 + 3 * n),
            "directions in and out, tangential vectors, cos/sin z",
        ),
        CostRow(
            "refraction_by_addition",
            "fixed",
            refraction_fixed_ops(n),
            _I64 * (4 * 3 * n + 6 * n + 8),
            "topocentric_observed_q30: diurnal aberration then refraction by addition, Q30 directions in and out",
        ),
        CostRow(
            "apparent_place",
            "float32",
            apparent_place_ops(n),
            _F32 * (3 * n * 4 + n + 9 + 9),
            "catalogue vector, proper motion, parallax in; change accumulator, TOD direction out; includes the "
            "once-per-instant Earth state and precession-nutation matrix",
        ),
        CostRow(
            "apparent_place",
            "fixed",
            apparent_place_fixed_ops(n),
            _I64 * (5 * 3 * n + n + 4 * n + 20),
            "apparent_place_vectors_q30 per star; the instant's quantities are the apparent_place_instant row",
        ),
        CostRow(
            "apparent_place_instant",
            "float64",
            apparent_instant_ops(),
            _F64 * (3 * 3 + 9) + _I64 * 20,
            "fixed_instant: once per frame, independent of N, soft float64 on a sensor without an FPU",
        ),
    ]


def _other_rows(n: int) -> list[CostRow]:
    """Not per star pair: a bank record's check, and the attitude from n stars."""
    return [
        CostRow(
            "bank_record_verify",
            "bytes",
            bank_record_verify_ops(),
            BANK_RECORD_BYTES + 4 * 256,
            "not per frame: at boot per bank and once per upload; CRC-32 by the 1 KiB table of export-c, one "
            "table look-up per byte besides the operations counted",
        ),
        CostRow(
            "attitude",
            "float32",
            attitude_ops(n),
            _F32 * (3 * n * 3 + n + 9 * 4),
            "b, r, weights; + one 3 x 3 SVD and two 3 x 3 solves (LAPACK, not counted)",
        ),
    ]


def format_table(rows: list[CostRow], n_stars: int, n_states: int) -> str:
    """The cost table as fixed-width text (``hostlink costs``)."""
    head = (
        f"{'function':<26} {'precision':<9} " + " ".join(f"{c:>8}" for c in CATEGORIES) + f" {'arith':>9} {'bytes':>7}"
    )
    lines = [f"cost per frame at N = {n_stars} stars, P = {2 * n_stars - 3} pairs, K = {n_states} states", head]
    for row in rows:
        flops = row.extra.get("flops", row.ops.flops)
        counts = " ".join(f"{getattr(row.ops, c) if row.ops != Ops() else '-':>8}" for c in CATEGORIES)
        lines.append(f"{row.function:<26} {row.precision:<9} {counts} {flops:>9} {row.memory_bytes:>7}")
    lines.append("")
    lines += [f"{row.function} ({row.precision}): {row.note}" for row in rows if row.note]
    return "\n".join(lines)


def cost_table_text(n_stars: int = 32, n_states: int = 10) -> str:
    """The cost table as text for ``n_stars`` in 3..MAX_STARS and ``n_states`` in 1..10; a one-line
    :class:`~hostlink.errors.UserError` otherwise. The estimator row is capped at its ``max_stars`` (it uses at
    most that many stars of a frame)."""
    from hostlink.errors import UserError
    from protocol.messages import MAX_STARS

    if not 3 <= int(n_stars) <= MAX_STARS:
        raise UserError(f"--stars must be 3..{MAX_STARS}, got {n_stars}")
    if not 1 <= int(n_states) <= 10:
        raise UserError(f"--states must be 1..10, got {n_states}")
    return format_table(cost_table(n_stars, n_states), n_stars, n_states)
