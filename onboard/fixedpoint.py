"""Fixed-point front end of the onboard estimator, for a sensor without an FPU (docs/architecture.md: onboard).

What runs per star and per frame runs here in integers: the camera model of docs/camera-model.md from a measured
centroid to a sensor-frame unit vector, and the interstar difference residuals of :mod:`onboard.interstar`. It is
the fixed-point twin of :func:`onboard.camera.pixels_to_unit` and :func:`onboard.interstar.difference_residuals`
(the same Weng formula, seed 000 eq. 7, term by term; ``tests/test_fixedpoint_camera.py`` holds it against them in
float64). The filter update (Bierman U-D, O(P K^2) per frame) stays in float32, which such a sensor runs with a
soft-float library, and so do the Jacobians, which need only ~1e-4 relative accuracy: see
:mod:`onboard.recursive` (``update(..., front_end=...)``). Each soft-float operation costs many integer
instructions; the front end is where the precision matters (the residual is a small difference of numbers near 1)
and where the per-star operations are, so it is the part written in integers.

Entry: :func:`update` is one frame of the estimator on such a sensor (``onboard.firmware.estimator_update`` calls it
for ``precision="fixed"``, in the emulated sensor and in ``hostlink replay`` alike): :func:`frame_front_end` takes the
centroids in the wire's Q10 steps and the catalogue in Q30, then ``onboard.recursive.update`` runs with this module's
residuals. The integer primitives :func:`rshift_round`, :func:`div_round`, :func:`isqrt` and :func:`bit_length` are
shared with the fixed-point site correction (``onboard.refraction.topocentric_observed_q30``).

Rounding: every right shift rounds to nearest, ties toward +infinity (``(a + 2^(n-1)) >> n``, :func:`rshift_round`).
Every operand stays below 2^34 and every product below 2^62.2, so int64 (< 2^63) never overflows (ranges proved
in the comments below; tested at the extremes against the same code run on exact Python integers, where the largest
product reached is 2^62: r^2 squared at the far corner of a detector with the principal point at a corner).

Formats (``Qn`` = integer times 2^-n; S = 2^s px is the smallest power of two >= the longer detector side, and a
*normalised* length is a length in px divided by S):

==================  =============================================  ==================================================
quantity            format                                         range
==================  =============================================  ==================================================
centroid x, y       Q10 px (the wire's steps, protocol.messages)   on the detector: [-2^9, 2^10 W - 2^9]
x0, y0              Q(30 - s) px  (= Q30 normalised)                on the detector
u, v                Q30 normalised (u / S)                         |U| <= 2^30 (|u| <= max(W, H) <= S)
u^2, uv, v^2, r^2   Q30 normalised^2                               <= 2^30, 2^30, 2^30, 2^31
r^4, r^6            Q30                                            <= 2^32, 2^33
K1 = k1 S^2, K2 = k2 S^4, K3 = k3 S^6,                            block floating point: m 2^-e, 2^27 <= |m| <= 2^28
P = p S, S' = s S   (normalised coefficients, one exponent each)  (a float32 coefficient is held exactly), e <= 62
radial rho          Q30 (dimensionless)                            |rho| <= 2^30 (range condition below)
u', v'              Q30 normalised                                 |U'| < 2.5 2^30
w = (u', v', F)     Q(qw) normalised, qw = 30 - ceil(log2 max(F/S, 4))  |w_c| <= 2^30
|w|^2               Q(2 qw)                                        < 3 2^60
1 / sqrt(alpha)     Q30, alpha = |w|^2 scaled to [1/4, 1] (odd shift)  [2^30, 2^31]
unit vector b       Q30                                            |B_c| <= 2^30 + 1
catalogue r         Q30 (quantised once, at catalogue build)       |R_c| <= 2^30
e_ij                Q61, exact from the Q30 vectors                |E| <= 2^62 + 2^34
==================  =============================================  ==================================================

Range condition (:func:`fixed_camera` refuses a set outside it with :class:`FixedRangeError`): the principal point
on the detector, s <= 20, S / 8 <= F <= 2^20 px (a diagonal field up to ~160 deg; :data:`MAX_FOCAL_PX`), and at the
farthest corner (normalised radius rho_max <= sqrt 2) ``|K1| rho_max^2 + |K2| rho_max^4 + |K3| rho_max^6 +
rho_max max(3|P1| + |P2| + |S1|, 3|P2| + |P1| + |S2|) <= 1``, i.e. the distortion correction never exceeds the
radius. Real lenses are far inside (seed 004's corrects 0.12 % of the radius at its farthest corner);
:func:`onboard.params.validate_params` bounds positive radial distortion by monotonicity (k1 r^2 < 1/3) but not
negative, so this check is the fixed-point sensor's own.

Error against the float64 model at the same parameters (derived from the formats, :func:`error_bounds_q30`: u', v'
within D Q30 steps, D = 2 + rho_max (3/2 + the normalised coefficients times their powers' rounding errors) + the
tangential terms, and each component of b within 2^-30 (4 + sqrt 2 (D + 2) S / F); measured in
``tests/test_fixedpoint_camera.py`` for the seed-004 camera, S = 1024 px, F = 5852 px: D = 3.1 steps (S 2^-30 =
9.5e-7 px; measured 2.3), b within 5.3 steps of 2^-30 (2.9e-5 px on the detector; measured 1.5 steps, 8e-6 px));
e_ij within |b_i - b_j| 2 sqrt(3) of that, under 2e-3 of the pair's noise at 0.05 px centroid noise (measured:
2.3e-4 at most, 6e-5 RMS; 1.6e-5 px at most). A large normalised coefficient (strong distortion where rho_max is
small, e.g. a strip detector with the principal point centred) multiplies its power's rounding: D grows with it
(``tests/test_fixedpoint_camera_space.py`` draws cameras over the supported range against these bounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard import recursive
from protocol.messages import CENTROID_STEPS_PER_PX, dequantise_px, quantise_px

#: Bits of the centroid's fractional part on the wire (2^-10 px = protocol.messages.CENTROID_LSB_PX).
CENTROID_FRAC_BITS = 10
assert 1 << CENTROID_FRAC_BITS == CENTROID_STEPS_PER_PX
#: Fractional bits of normalised lengths, unit vectors and the radial factor.
Q = 30
#: Fractional bits of the interstar residual e_ij (exact from Q30 vectors: (2^-30)^2 / 2).
E_FRAC_BITS = 2 * Q + 1
#: Largest detector shift s (S = 2^s px): the Q10 centroid must fit the Q(30 - s) grid.
MAX_DETECTOR_SHIFT = Q - CENTROID_FRAC_BITS
#: Longest focal length F [px]: a Q30 unit vector's grid is F 2^-30 px on the detector, no coarser than the wire's Q10
#: centroid steps (2^-10 px) up to F = 2^20 px; beyond it the front end would lose precision silently (figures in
#: docs/camera-model.md, "Supported cameras") and, from F / S ~ 2^93, shift an int64 by 64 bits or more. With S >= 2
#: it also bounds F / S <= 2^19, so w's fractional bits qw >= 11.
MAX_FOCAL_PX = float(1 << (Q - CENTROID_FRAC_BITS))
#: Mantissa bits of a block-floating-point coefficient (float32's 24 bits fit exactly).
COEF_BITS = 28
#: Largest coefficient exponent (a right shift of an int64).
COEF_MAX_EXP = 62
#: Newton iterations of the reciprocal square root from the 25-entry table (relative error e -> 1.5 e^2:
#: 3.1e-2 -> 1.4e-3 -> 3.1e-6 -> 1.5e-11, below Q30's 2^-30 = 9.3e-10 after three).
RSQRT_ITERATIONS = 3
#: Table of 1/sqrt(alpha) in Q30 at the centre of each bin of alpha = a 2^-31, bins a >> 26 = 8..32:
#: isqrt(2^66 / (2 i + 1)) = 2^30 sqrt(32 / (i + 1/2)), in [2^30, 2^31) (built with integers only).
RSQRT_TABLE = np.array([math.isqrt((1 << 66) // (2 * i + 1)) for i in range(8, 33)], dtype=np.int64)
#: The bin a >> 26 of the table's first entry: the entry for a is RSQRT_TABLE[(a >> 26) - RSQRT_TABLE_FIRST].
RSQRT_TABLE_FIRST = 8


class FixedRangeError(ValueError):
    """A parameter set, or a centroid, outside the ranges the fixed-point formats are proved for."""


@dataclass(frozen=True)
class FixedCamera:
    """A camera model vector in the front end's formats (see the module docstring).

    ``coef_m`` / ``coef_e`` are the normalised K1 K2 K3 P1 P2 S1 S2 as m 2^-e. ``theta_q`` is the model vector
    (F in px, float64, exact) that these integers represent: what the front end evaluates."""

    s: int  # detector shift, S = 2^s px
    x0_q: int  # Q30 normalised
    y0_q: int
    coef_m: tuple[int, ...]
    coef_e: tuple[int, ...]
    qw: int  # fractional bits of w
    f_w: int  # F in Q(qw) normalised
    image_size_px: tuple[int, int]
    theta_q: np.ndarray


def rshift_round(a, n):
    """a 2^-n rounded to the nearest integer, ties toward +infinity: (a + 2^(n-1)) >> n, for n >= 1 (scalar or
    array). Works on int64 arrays and on object arrays of Python integers (the exact reference in the tests)."""
    return (a + (1 << (n - 1))) >> n


def _block_float(value: float) -> tuple[int, int]:
    """value -> (m, e) with value ~= m 2^-e, 2^27 <= |m| <= 2^28 (round half even), e <= 62 (smaller values keep
    e = 62 and a smaller m). Exact for a float32 (24-bit mantissa)."""
    if value == 0.0:
        return 0, COEF_MAX_EXP
    frac, exp = math.frexp(value)  # value = frac 2^exp, 1/2 <= |frac| < 1
    e = COEF_BITS - exp
    if e > COEF_MAX_EXP:
        e = COEF_MAX_EXP
    return round(math.ldexp(value, e)), e


def detector_shift(image_size_px: tuple[int, int]) -> int:
    """s with S = 2^s the smallest power of two >= the longer detector side (s >= 1)."""
    return max(1, (int(max(image_size_px)) - 1).bit_length())


def distortion_share(s: int, x0_q: int, y0_q: int, image_size_px: tuple[int, int], coef: list[float]) -> float:
    """The range condition's sum (module docstring) at the farthest corner: the distortion correction as a fraction
    of the radius, <= 1 in range (float64 on 10 values; every bound has a factor >= 1.6 to spare). ``coef``: the
    normalised K1 K2 K3 P1 P2 S1 S2 as held (m 2^-e); the principal point as held (Q30 normalised)."""
    w, h = image_size_px
    corners_x = (-0.5 - math.ldexp(x0_q, s - Q), w - 0.5 - math.ldexp(x0_q, s - Q))
    corners_y = (-0.5 - math.ldexp(y0_q, s - Q), h - 0.5 - math.ldexp(y0_q, s - Q))
    scale_px = float(1 << s)
    rho2 = max(cx * cx + cy * cy for cx in corners_x for cy in corners_y) / (scale_px * scale_px)
    rho = math.sqrt(rho2)
    k1, k2, k3, p1, p2, s1, s2 = coef
    c_rad = abs(k1) * rho2 + abs(k2) * (rho2 * rho2) + abs(k3) * (rho2 * rho2 * rho2)
    c_tan = rho * max(3 * abs(p1) + abs(p2) + abs(s1), 3 * abs(p2) + abs(p1) + abs(s2))
    return c_rad + c_tan


def fixed_camera(theta: np.ndarray, image_size_px: tuple[int, int]) -> FixedCamera:
    """Model vector (F px, x0, y0, k1..s2; float32 or float64) -> the front end's formats.

    Done once per linearisation (10 values: on a sensor, a few soft-float conversions), not per star. A float32
    vector converts exactly (28-bit mantissas; F's grid is finer than its float32 ulp whenever F >= S/8) except a
    principal point below 2^(s - 7) px, rounded to the Q(30 - s) px grid (by at most 2^(s - 31) px);
    ``theta_q`` is the exact value used, so a caller can account for the rounding.
    Raises :class:`FixedRangeError` outside the range condition of the module docstring."""
    w, h = (int(image_size_px[0]), int(image_size_px[1]))
    s = detector_shift((w, h))
    if s > MAX_DETECTOR_SHIFT:
        raise FixedRangeError(f"detector side {max(w, h)} px exceeds the fixed-point range (2^{MAX_DETECTOR_SHIFT})")
    t = [float(v) for v in np.asarray(theta, dtype=np.float64)]
    if not all(math.isfinite(v) for v in t):
        raise FixedRangeError("parameters must be finite")
    f_px, x0, y0 = t[0], t[1], t[2]
    if not (-0.5 <= x0 <= w - 0.5 and -0.5 <= y0 <= h - 0.5):
        raise FixedRangeError(f"principal point ({x0!r}, {y0!r}) px is off the detector")
    scale_px = float(1 << s)
    if not f_px >= scale_px / 8:
        raise FixedRangeError(f"focal length {f_px:.6g} px is below S/8 = {scale_px / 8:.0f} px (field too wide)")
    if not f_px <= MAX_FOCAL_PX:
        raise FixedRangeError(
            f"focal length {f_px:.6g} px is above 2^20 = {MAX_FOCAL_PX:.0f} px (Q30 unit vectors coarser than the "
            "Q10 centroids)"
        )
    x0_q = round(math.ldexp(x0, Q - s))  # exact: ldexp scales by a power of two
    y0_q = round(math.ldexp(y0, Q - s))
    # normalised coefficients: k1 S^2, k2 S^4, k3 S^6, p S, s S (powers of two: exact)
    powers = (2, 4, 6, 1, 1, 1, 1)
    blocks = [_block_float(math.ldexp(t[3 + k], s * powers[k])) for k in range(7)]
    coef = [math.ldexp(m, -e) for m, e in blocks]
    share = distortion_share(s, x0_q, y0_q, (w, h), coef)
    if not share <= 1.0:
        raise FixedRangeError(
            f"distortion correction up to {100 * share:.0f} % of the radius exceeds the fixed-point range (100 %)"
        )
    # w = (u', v', F) normalised: |u'| < 2.5 (below), so max(F/S, 4) 2^qw <= 2^30 bounds every component
    cap = max(f_px / scale_px, 4.0)
    frac, exp = math.frexp(cap)
    qw = Q - (exp - 1 if frac == 0.5 else exp)  # 30 - ceil(log2 cap) <= 28
    f_w = round(math.ldexp(f_px, qw - s))
    theta_q = np.array(
        [math.ldexp(f_w, s - qw), math.ldexp(x0_q, s - Q), math.ldexp(y0_q, s - Q)]
        + [math.ldexp(c, -s * powers[k]) for k, c in enumerate(coef)],
        dtype=np.float64,
    )
    return FixedCamera(
        s=s,
        x0_q=x0_q,
        y0_q=y0_q,
        coef_m=tuple(m for m, _ in blocks),
        coef_e=tuple(e for _, e in blocks),
        qw=qw,
        f_w=f_w,
        image_size_px=(w, h),
        theta_q=theta_q,
    )


def farthest_radius_normalised(cam: FixedCamera) -> float:
    """rho_max: the distance from the principal point (as held, x0_q, y0_q) to the farthest detector corner over S."""
    w, h = cam.image_size_px
    x0, y0 = math.ldexp(cam.x0_q, cam.s - Q), math.ldexp(cam.y0_q, cam.s - Q)
    du = max(abs(-0.5 - x0), abs(w - 0.5 - x0))
    dv = max(abs(-0.5 - y0), abs(h - 0.5 - y0))
    return math.ldexp(math.hypot(du, dv), -cam.s)


def error_bounds_q30(cam: FixedCamera) -> tuple[float, float]:
    """The front end's error against the float64 model at ``cam.theta_q``, in Q30 steps (2^-30), derived from the
    formats: (D, B) with D bounding u', v' (normalised) and B each component of b, for any centroid on the detector.

    D adds the roundings of :func:`ideal_offsets_q30` (each half a step) and the powers' errors each coefficient
    amplifies (rho = rho_max, K = |normalised coefficient|): delta r2 <= 1, delta r4 <= 1/2 + 2 rho^2,
    delta r6 <= 1/2 + 3/2 rho^2 + 3 rho^4, so delta rho_radial <= 3/2 + K1 + K2 (1/2 + 2 rho^2) + K3 (1/2 + 3/2 rho^2
    + 3 rho^4) and D = 2 + rho delta rho_radial + 2|P1| + |P2| + |S1| (v': P1 and P2, S1 and S2 swapped).
    B = 4 + sqrt 2 (D + 2) S / F: the final rounding and the reciprocal square root (4), the offsets and w's grid
    (2 steps when F < 4S, within the 4 otherwise) over |w| >= F / S through the projection I - b b^T (norm 1).
    Small coefficients give D ~ 4 (the seed-004 camera: 3.1); a large one (a strong distortion where rho_max is
    small, e.g. a strip detector) multiplies its power's rounding."""
    rho = farthest_radius_normalised(cam)
    k1, k2, k3, p1, p2, s1, s2 = (abs(math.ldexp(m, -e)) for m, e in zip(cam.coef_m, cam.coef_e, strict=True))
    r2 = rho * rho
    radial = 1.5 + k1 + k2 * (0.5 + 2 * r2) + k3 * (0.5 + 1.5 * r2 + 3 * r2 * r2)
    d = 2 + rho * radial + max(2 * p1 + p2 + s1, 2 * p2 + p1 + s2)
    return d, 4 + math.sqrt(2) * (d + 2) * math.ldexp(1.0, cam.s) / float(cam.theta_q[0])


def on_detector(x_steps: np.ndarray, y_steps: np.ndarray, image_size_px: tuple[int, int]) -> np.ndarray:
    """Mask of centroids (Q10 px) on the detector [-0.5, W - 0.5] x [-0.5, H - 0.5]: the only ones the front end
    takes (a star cannot be imaged elsewhere; the formats' range proof assumes it)."""
    half = 1 << (CENTROID_FRAC_BITS - 1)
    w, h = (int(image_size_px[0]), int(image_size_px[1]))
    return (
        (x_steps >= -half)
        & (x_steps <= (w << CENTROID_FRAC_BITS) - half)
        & (y_steps >= -half)
        & (y_steps <= (h << CENTROID_FRAC_BITS) - half)
    )


def _coef_term(power_q30, cam: FixedCamera, k: int):
    """power (Q30, < 2^34) times coefficient k (m 2^-e, |m| <= 2^28) -> Q30: product < 2^62."""
    return rshift_round(power_q30 * cam.coef_m[k], cam.coef_e[k])


def ideal_offsets_q30(x_steps, y_steps, cam: FixedCamera):
    """Measured centroids (Q10 px) -> ideal offsets (u', v') = (u - dx, v - dy), Q30 normalised (px / S).

    The Weng correction at the measured point (docs/camera-model.md, seed 000 eq. 7), grouped by coefficient as in
    :func:`onboard.camera.ideal_offset_jacobians`: with g1 = s1 + p1, g2 = s2 + p2, g3 = 2 p1, g4 = 2 p2,
    dx = p1 (3u^2 + v^2) + 2 p2 uv + s1 r^2 + u (k1 r^2 + k2 r^4 + k3 r^6) and
    dy = p2 (u^2 + 3v^2) + 2 p1 uv + s2 r^2 + v (k1 r^2 + k2 r^4 + k3 r^6).
    Raises :class:`FixedRangeError` when a centroid lies off the detector (|u| > S)."""
    shift = MAX_DETECTOR_SHIFT - cam.s  # Q10 px -> Q(30 - s) px, s <= 20
    u = (x_steps << shift) - cam.x0_q  # |u| <= max(W, H) <= S  ->  |U| <= 2^30
    v = (y_steps << shift) - cam.y0_q
    if np.any(np.abs(u) > (1 << Q)) or np.any(np.abs(v) > (1 << Q)):
        raise FixedRangeError("centroid off the detector")
    uu = rshift_round(u * u, Q)  # U^2 <= 2^60  ->  <= 2^30
    vv = rshift_round(v * v, Q)
    uv = rshift_round(u * v, Q)  # |uv| <= 2^30
    r2 = uu + vv  # <= 2^31 (rho^2 <= 2)
    r4 = rshift_round(r2 * r2, Q)  # r2^2 <= 2^62  ->  <= 2^32
    r6 = rshift_round(rshift_round(r4, 1) * r2, Q - 1)  # r4 r2 could reach 2^63: halve r4 first, <= 2^62
    radial = _coef_term(r2, cam, 0) + _coef_term(r4, cam, 1) + _coef_term(r6, cam, 2)  # |rho| <= 2^30
    ru = rshift_round(u * radial, Q)  # |U rho| <= 2^60
    rv = rshift_round(v * radial, Q)
    uv2 = uv + uv  # 2uv, <= 2^31
    dx = ru + _coef_term(3 * uu + vv, cam, 3) + _coef_term(uv2, cam, 4) + _coef_term(r2, cam, 5)
    dy = rv + _coef_term(uu + 3 * vv, cam, 4) + _coef_term(uv2, cam, 3) + _coef_term(r2, cam, 6)
    return u - dx, v - dy  # |dx| <= rho_max <= sqrt 2: |U'| < 2.5 2^30


def rsqrt_q30(n2):
    """1 / sqrt(n2) for integers 2^50 <= n2 < 2^62, as (Y, k): 1/sqrt(n2) = Y 2^-30 2^-k, Y in Q30 in [2^30, 2^31].

    Normalise n2 = alpha 2^(31 + sh) with alpha = a 2^-31 in [1/4, 1] and 31 + sh even (a = n2 >> sh rounded, its
    top 30-31 bits); then 1/sqrt(n2) = alpha^-1/2 2^-(31 + sh)/2, so k = (31 + sh) / 2. alpha^-1/2 starts from the
    table at a >> 26 and takes :data:`RSQRT_ITERATIONS` Newton steps y <- y (3 - alpha y^2) / 2 in integers."""
    length = bit_length(n2)  # 51..62
    sh = length - Q - 1  # a in [2^30, 2^31)
    sh = sh + ((sh + 1) & 1)  # make sh odd (then a in [2^29, 2^30)): 31 + sh even
    a = rshift_round(n2, sh)  # in [2^29, 2^31]
    y = RSQRT_TABLE[((a >> 26) - RSQRT_TABLE_FIRST).astype(np.intp)].astype(a.dtype)  # Q30, rel. error <= 3.1 %
    for _ in range(RSQRT_ITERATIONS):
        t1 = rshift_round(a * y, Q + 1)  # a y <= 2^31 1.031 2^31 < 2^63; t1 = alpha y in Q30
        t2 = rshift_round(t1 * y, Q)  # alpha y^2 ~ 1 in Q30; t1 y <= 2^31.1 2^31.1
        y = rshift_round(y * (3 * (1 << Q) - t2), Q + 1)  # y (3 - alpha y^2) / 2; factors <= 2^31.1 each (3.1 % start)
    return y, (Q + 1 + sh) >> 1


def bit_length(x):
    """Bit length of integers 0 <= x < 2^63 (a CLZ instruction on a sensor): binary search with shifts."""
    n = np.zeros_like(x)
    y = x
    for k in (32, 16, 8, 4, 2, 1):
        big = (y >> k) > 0
        n = n + np.where(big, k, 0)
        y = np.where(big, y >> k, y)
    return n + (y > 0)


def div_round(num, den):
    """num / den rounded to nearest, ties toward +infinity, for den > 0: floor((num + floor(den / 2)) / den) (an
    int64 division: a library call on cores without a 64-bit divider)."""
    return (num + (den >> 1)) // den


#: Newton iterations of :func:`isqrt`: from x0 in [sqrt n, 2 sqrt n] the relative error goes 1 -> 1/4 -> 2.5e-2 ->
#: 3e-4 -> 5e-8 -> 1e-15, under one unit of a root < 2^31 after six; the seventh and eighth reach the floor.
ISQRT_ITERATIONS = 8


def isqrt(n):
    """floor(sqrt(n)) for integers 0 <= n < 2^62 (int64, or Python integers in an object array): Newton's method in
    integers from the power of two 2^ceil(bits/2) >= sqrt(n); the iterates decrease to the floor and stay there."""
    n = np.asarray(n)
    x = np.maximum(1 << ((bit_length(n) + 1) >> 1), 1)
    for _ in range(ISQRT_ITERATIONS):
        x = np.minimum(x, np.maximum((x + n // x) >> 1, 1))  # stays >= 1: n = 0 never divides by 0
    return np.where(n > 0, x, 0)


def offsets_to_unit_q30(u_ideal, v_ideal, cam: FixedCamera):
    """Ideal offsets (Q30 normalised) -> sensor-frame unit vectors b = (u', v', F) / |.| in Q30, shape (N, 3)."""
    down = Q - cam.qw  # >= 2
    wu = rshift_round(u_ideal, down)  # |u'| < 2.5 <= 4: |wu| <= 2^30 (max(F/S, 4) 2^qw <= 2^30)
    wv = rshift_round(v_ideal, down)
    wf = cam.f_w  # F 2^qw / S in [2^(qw - 3), 2^30]; one value per frame (wf^2 once, not per star)
    n2 = wu * wu + wv * wv + wf * wf  # < 3 2^60; >= wf^2 >= 2^50 (F >= S/8 and qw = 28 when F < 4S)
    y, k = rsqrt_q30(n2)
    b = np.empty((np.shape(wu)[0], 3), dtype=np.result_type(wu))
    b[:, 0] = rshift_round(wu * y, k)  # |w_c| <= 2^30, y <= 2^31: product <= 2^61
    b[:, 1] = rshift_round(wv * y, k)
    b[:, 2] = rshift_round(wf * y, k)
    return b


def normalise_q30(w):
    """Integer vectors (N, 3) with |w_c| <= 2^30 and 2^50 <= |w|^2 < 2^62, at any common scale -> unit vectors w / |w|
    in Q30: :func:`rsqrt_q30` of |w|^2, then each component times it (|w_c| y <= 2^30 2^31 = 2^61), as
    :func:`offsets_to_unit_q30` does with its per-frame third component."""
    n2 = w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1] + w[:, 2] * w[:, 2]
    y, k = rsqrt_q30(n2)
    return rshift_round(w * y[:, None], k[:, None])


def pixels_to_unit_q30(x_steps, y_steps, cam: FixedCamera):
    """Measured centroids (Q10 px, int64) -> sensor-frame unit vectors (N, 3), Q30: the fixed-point twin of
    :func:`onboard.camera.pixels_to_unit`."""
    u_i, v_i = ideal_offsets_q30(x_steps, y_steps, cam)
    return offsets_to_unit_q30(u_i, v_i, cam)


def quantise_unit_q30(r: np.ndarray) -> np.ndarray:
    """Catalogue unit vectors (float) -> Q30 int64 (round half even). Done once when the catalogue is built
    (ground software), not per frame; the error, 2^-31 per component, is 1/64 of float32's 2^-25."""
    return np.rint(np.ldexp(np.asarray(r, dtype=np.float64), Q)).astype(np.int64)


def difference_residuals_q61(b_q30, r_q30, i, j):
    """e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 in Q61, exact (the fixed-point twin of
    :func:`onboard.interstar.difference_residuals`). Components of a difference of two Q30 unit vectors are at
    most 2^31 + 2, so |d|^2 <= 4 2^60 (1 + 2^-28) and the difference of two such fits int64."""
    db = b_q30[i] - b_q30[j]
    dr = r_q30[i] - r_q30[j]
    sb = db[:, 0] * db[:, 0] + db[:, 1] * db[:, 1] + db[:, 2] * db[:, 2]  # Q60, partial sums <= the total
    sr = dr[:, 0] * dr[:, 0] + dr[:, 1] * dr[:, 1] + dr[:, 2] * dr[:, 2]
    return sb - sr  # (sb - sr) 2^-60 / 2 = (sb - sr) 2^-61


def residuals_to_float(e_q61: np.ndarray, dtype: type | np.dtype) -> np.ndarray:
    """Q61 residuals -> the filter's float (one rounding: int64 -> float, then an exact power-of-two scaling)."""
    dt = np.dtype(dtype)
    return np.asarray(e_q61).astype(dt) * dt.type(2.0**-E_FRAC_BITS)


@dataclass(frozen=True)
class FixedFrame:
    """One frame's integer inputs for the fixed-point front end: centroids in Q10 px (the wire's steps) and the
    identified stars' catalogue unit vectors in Q30, one row per input star. Passed to
    :func:`onboard.recursive.update` as ``front_end``."""

    x_steps: np.ndarray  # (N,) int64
    y_steps: np.ndarray  # (N,) int64
    r_q30: np.ndarray  # (N, 3) int64
    image_size_px: tuple[int, int]

    def residuals(self, theta: np.ndarray, rows: np.ndarray, pi: np.ndarray, pj: np.ndarray):
        """Residuals e (P,) of the pairs (pi, pj) of the stars ``rows`` at the model vector ``theta`` (converted to
        the fixed formats), as ``theta``'s float dtype, and the float64 model vector actually evaluated."""
        cam = fixed_camera(theta, self.image_size_px)
        b = pixels_to_unit_q30(self.x_steps[rows], self.y_steps[rows], cam)
        e = difference_residuals_q61(b, self.r_q30[rows], pi, pj)
        return residuals_to_float(e, np.asarray(theta).dtype), cam.theta_q


#: Largest |centroid| [px] taken before the detector check: keeps the Q10 conversion inside int64 for any float input
#: (everything this far off the detector is refused by :func:`on_detector` anyway).
_CENTROID_CLIP_PX = float(1 << 40)


def frame_front_end(
    x_px: np.ndarray, y_px: np.ndarray, r_ref: np.ndarray, identified: np.ndarray | None, image_size_px: tuple[int, int]
) -> tuple[FixedFrame, np.ndarray]:
    """One frame as a sensor without an FPU holds it: centroids [px] in the wire's Q10 steps (round half even, as
    :func:`protocol.messages.quantise_px`: the centroider's output format), catalogue unit vectors in Q30 (the
    integers a fixed-point catalogue stores, :func:`quantise_unit_q30`), and the mask of stars the front end takes:
    identified (``identified``, None = all), finite, and on the detector (:func:`on_detector`).
    Returns (the :class:`FixedFrame`, that mask)."""
    x = np.asarray(x_px, dtype=np.float64)
    y = np.asarray(y_px, dtype=np.float64)
    r = np.asarray(r_ref, dtype=np.float64).reshape(-1, 3)
    usable = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(r), axis=1)
    if identified is not None:
        usable &= np.asarray(identified, dtype=bool)
    clip = _CENTROID_CLIP_PX
    x_steps = quantise_px(np.clip(np.where(usable, x, 0.0), -clip, clip))
    y_steps = quantise_px(np.clip(np.where(usable, y, 0.0), -clip, clip))
    usable &= on_detector(x_steps, y_steps, image_size_px)
    r_q30 = quantise_unit_q30(np.where(usable[:, None], r, 0.0))
    return FixedFrame(x_steps, y_steps, r_q30, (int(image_size_px[0]), int(image_size_px[1]))), usable


def update(
    state: recursive.RecursiveState,
    x_px: np.ndarray,
    y_px: np.ndarray,
    r_ref: np.ndarray,
    identified: np.ndarray | None = None,
) -> recursive.FrameResult:
    """One frame of the onboard recursive estimator on a sensor without an FPU: :func:`onboard.recursive.update` with
    the residuals from this module's integer front end (:func:`frame_front_end`); the float32 (soft-float) filter and
    its Jacobians see the same Q10 centroids. Raises :class:`FixedRangeError` when the estimate has left the
    fixed-point range (:func:`fixed_camera`)."""
    front, usable = frame_front_end(x_px, y_px, r_ref, identified, state.nominal.image_size_px)
    r = np.where(usable[:, None], np.asarray(r_ref, dtype=np.float64).reshape(-1, 3), 0.0)
    return recursive.update(
        state, dequantise_px(front.x_steps), dequantise_px(front.y_steps), r, usable, front_end=front
    )
