"""Cost table of the onboard functions a port needs: arithmetic operations and working memory per frame at N stars,
in float32 and in fixed point, so a firmware engineer can budget the sensor on a given microcontroller
(``hostlink costs``; docs/port-kit.md).

Where the counts come from:

* Counted formulas, written from the code line by line (each function below names the lines it counts):
  :func:`pixel_to_direction_ops` (``onboard.camera.pixels_to_unit``), :func:`pixel_to_direction_fixed_ops`
  (``onboard.fixedpoint.pixels_to_unit_q30``), :func:`interstar_residual_ops` (``onboard.interstar
  .difference_residuals`` and its Q61 twin), :func:`interstar_jacobian_ops` (``difference_jacobian``) and
  :func:`bierman_update_ops` (``onboard.ud.bierman_update``). ``tests/test_portkit_costs.py`` holds each against
  an instrumented run of the code (:func:`count_operations`, a numpy array subclass that counts every element of
  every ufunc it goes through).
* Measured: functions whose structure is long (camera Jacobians, refraction, apparent place, attitude) are counted
  by running the reference code on N stars through :func:`count_operations`; the count is exact for the code as
  written (LAPACK calls inside ``np.linalg``, i.e. the attitude's one 3 x 3 SVD and 3 x 3 solve, are not seen and
  are listed as a constant).
* The estimator's whole frame is ``onboard.recursive.update_cost_flops`` (the sensor's own budget model,
  ``onboard.firmware.EstimatorBudget``), reused, not restated.

Operations are counted as the reference code performs them (numpy on whole arrays): a C port that exploits the unit
upper-triangular U in the U-D update, or replaces a division by 2 with a multiplication, does less. ``add`` counts
additions and subtractions, ``cmp`` comparisons and selections, ``shift`` integer shifts and masks (fixed point),
``trig`` sin/cos/tan/atan2/asin. Memory is the working buffers one call needs (inputs, outputs, intermediates the
code keeps), in bytes: float32 4, int64 8 (fixed point's Q30/Q61 values), int32 4 (Q10 centroids).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

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
        _Counted.tally.update(_ufunc_ops(ufunc, method, args, result))
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


def _ufunc_ops(ufunc, method: str, args, result) -> dict[str, int]:
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
        if method == "accumulate" or a.ndim == 0:
            return {category: int(np.size(result)) - int(np.size(result)) // max(a.shape[0] if a.ndim else 1, 1)}
        return {category: int(a.size - np.size(result))}
    return {}


#: numpy constructors that take no array (so no dispatch): instrumented while counting, so buffers a function
#: allocates inside itself count too.
_CONSTRUCTORS = ("zeros", "empty", "ones", "eye", "full")


def counted(array: np.ndarray) -> np.ndarray:
    """``array`` as an instrumented array (same data and dtype): every ufunc it meets is counted."""
    return np.asarray(array).view(_Counted)


def count_operations(fn: Callable, *args, **kwargs) -> Ops:
    """Operations one call ``fn(*args, **kwargs)`` performs on arrays (pass the inputs through :func:`counted`):
    every element of every ufunc, matmul/dot/einsum/cross as their multiplications and additions, reductions as
    their additions. Buffers the function allocates (np.zeros, np.empty, ...) are instrumented for the duration of
    the call (the numpy constructors are wrapped, then restored). Not seen: work on Python or numpy scalars
    (per-call constants) and LAPACK calls (np.linalg)."""
    saved = {name: getattr(np, name) for name in _CONSTRUCTORS}

    def instrumented(constructor):
        return lambda *a, **k: constructor(*a, **k).view(_Counted)

    _Counted.tally = Counter()
    try:
        for name, constructor in saved.items():
            setattr(np, name, instrumented(constructor))
        fn(*args, **kwargs)
    finally:
        for name, constructor in saved.items():
            setattr(np, name, constructor)
    tally = _Counted.tally
    return Ops(**{c: int(tally.get(c, 0)) for c in CATEGORIES})


# ------------------------------------------------------------------------------------------ counted formulas
def pixel_to_direction_ops(n_stars: int) -> Ops:
    """``onboard.camera.pixels_to_unit`` for N stars. Per star: u, v = x - x0, y - y0 (2 add); distortion_px:
    r2 = u u + v v (2 mul, 1 add), radial = r2 (k1 + r2 (k2 + r2 k3)) (3 mul, 2 add), dx and dy each 7 mul and
    3 add; u - dx, v - dy (2 add); offsets_to_unit: w w (3 mul), its sum (2 add), sqrt (1), w / |w| (3 div).
    The 4 additions g1..g4 of the coefficients are per call."""
    n = int(n_stars)
    return Ops(mul=22 * n, add=15 * n, div=3 * n, sqrt=n)


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
    rsqrt = Ops(mul=9, add=7 + 2 + 2 + 2 + 1 + 12 + 1, shift=12 + 1 + 2 + 1 + 9 + 1, cmp=7)
    to_unit = Ops(mul=2 + 3, add=2 + 2 + 6, shift=2 + 6) + rsqrt
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


def cost_table(n_stars: int = 32, n_states: int = 10, config: RecursiveConfig | None = None) -> list[CostRow]:
    """The cost table at ``n_stars`` stars and ``n_states`` estimated parameters (docs/port-kit.md)."""
    n, k = int(n_stars), int(n_states)
    if n < 3:
        raise ValueError(f"the cost table needs at least 3 stars, got {n}")
    p = 2 * n - 3
    cfg = config or RecursiveConfig()
    n_est = min(n, cfg.max_stars)  # the estimator uses at most max_stars stars of a frame
    p_est, linearisations = 2 * n_est - 3, cfg.max_iterations + 2
    f32, i64, i32 = 4, 8, 4
    rows = [
        CostRow(
            "pixel_to_direction",
            "float32",
            pixel_to_direction_ops(n),
            f32 * (2 * n + 10 + 3 * n),
            "x, y, theta in; b (N, 3) out",
        ),
        CostRow(
            "pixel_to_direction",
            "fixed",
            pixel_to_direction_fixed_ops(n),
            i32 * 2 * n + i64 * (3 * n + 2 * n + 20),
            "Q10 centroids in; Q30 u', v' and b (N, 3) out; camera in block floating point",
        ),
        CostRow(
            "unit_vector_jacobians",
            "float32",
            unit_vector_jacobian_ops(n),
            f32 * (3 * n + 30 * n + 6 * n + 9 * n + 30 * n + 20 * n),
            "b, db/dtheta (N, 3, 10), db/dxy (N, 3, 2) and the (N, 3, 3) projector; fixed-point sensors run this "
            "in float32 (soft float)",
        ),
        CostRow("interstar_residual", "float32", interstar_residual_ops(p), f32 * (6 * n + p), "P = 2N - 3 pairs"),
        CostRow(
            "interstar_residual", "fixed", interstar_residual_ops(p, fixed=True), i64 * (6 * n + p), "Q30 in, Q61 out"
        ),
        CostRow(
            "interstar_jacobian",
            "float32",
            interstar_jacobian_ops(p, k),
            f32 * (3 * n + 3 * n * k + p * k),
            "H (P, K)",
        ),
        CostRow(
            "bierman_update",
            "float32",
            bierman_update_ops(k),
            f32 * (k * k + 2 * k + 4 * k + k * k),
            "one whitened pair; P of them per linearisation; fixed-point sensors: float32 soft float",
        ),
        CostRow(
            "estimator_frame",
            "float32",
            Ops(),
            f32 * (5 * n + 30 * n + 6 * n + p + p * k + p * p + p * (k + 1) + k * k + 6 * k),
            "worst case of onboard.recursive.update (update_cost_flops): (max_iterations + 2) linearisations of "
            "P^3/3 + P^2 (K + 1) + 6 P K^2 + 40 N K flops",
            {"flops": update_cost_flops(n, k, config)},
        ),
        CostRow(
            "estimator_frame_front_end",
            "fixed",
            (pixel_to_direction_fixed_ops(n_est) + interstar_residual_ops(p_est, fixed=True)).scaled(linearisations),
            i32 * 2 * n_est + i64 * (3 * n_est + 3 * n_est + 2 * n_est + p_est),
            "a sensor without an FPU: the integer front end once per linearisation (max_iterations + 2), on top "
            "of the estimator_frame flops in float32 soft float (the front end replaces no float work: the "
            "Jacobians still need b)",
        ),
        CostRow(
            "refraction_by_addition",
            "float32",
            refraction_ops(n),
            f32 * (3 * n * 3 + 3 * n),
            "directions in and out, tangential vectors, cos/sin z",
        ),
        CostRow(
            "apparent_place",
            "float32",
            apparent_place_ops(n),
            f32 * (3 * n * 4 + n + 9 + 9),
            "catalogue vector, proper motion, parallax in; change accumulator, TOD direction out; includes the "
            "once-per-instant Earth state and precession-nutation matrix",
        ),
        CostRow(
            "attitude",
            "float32",
            attitude_ops(n),
            f32 * (3 * n * 3 + n + 9 * 4),
            "b, r, weights; + one 3 x 3 SVD and two 3 x 3 solves (LAPACK, not counted)",
        ),
    ]
    return rows


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
