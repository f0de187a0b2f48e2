"""An attitude in the forms engineers and astronomers use (issue 31): the quaternion, the boresight's right ascension,
declination and roll, and a FITS world coordinate system (TAN with SIP distortion) of the calibrated camera.

Conventions (docs/file-formats.md, "Attitude file"):

* ``C`` (3, 3) maps reference-frame components to sensor-frame components, ``b = C r`` (the sensor frame: +z the
  boresight, +x along increasing column, +y along increasing row; docs/camera-model.md).
* The quaternion ``q = (q0, q1, q2, q3)`` is scalar first, ``q0 >= 0``, and is the rotation that carries the
  reference axes onto the sensor axes (Hamilton's product; ``scipy.spatial.transform.Rotation.from_matrix(C.T)``).
  In Shuster's (1993, "A survey of attitude representations", eq. 161) attitude-matrix form, with ``v = (q1, q2,
  q3)``: ``C = (q0^2 - |v|^2) I + 2 v v^T - 2 q0 [v x]``.
* The boresight is the sensor's +z axis, the third row of ``C``; roll is the angle from the image's -y axis (up) to
  the celestial north projected into the image, measured toward +x (what ``hostlink identify`` prints).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from math import comb

import numpy as np

from onboard.camera import distortion_px, unit_to_radec


def attitude_quaternion(c: np.ndarray) -> np.ndarray:
    """Quaternion (q0, q1, q2, q3), scalar first and q0 >= 0, of the attitude matrix ``c`` (module docstring), by
    Shepperd's method (Shepperd 1978, J. Guidance Control 1(3); Shuster 1993 eq. 163-168): of 4 q_i^2 (from the
    trace and the diagonal) the largest is taken first, and the other three from the off-diagonal sums and
    differences divided by it, so no division by a small number. ``c`` (3, 3) or (N, 3, 3); NaN matrices give NaN
    quaternions."""
    a = np.asarray(c, dtype=np.float64).reshape(-1, 3, 3)
    d0, d1, d2 = a[:, 0, 0], a[:, 1, 1], a[:, 2, 2]
    tr = d0 + d1 + d2
    four_sq = np.stack([1 + tr, 1 + 2 * d0 - tr, 1 + 2 * d1 - tr, 1 + 2 * d2 - tr], axis=1)  # 4 q_i^2
    # 4 q_i q_j for every pair: (0, k) from the differences, (i, j) from the sums of the off-diagonal elements
    pair = np.empty((a.shape[0], 4, 4))
    pair[:, 0, 1] = pair[:, 1, 0] = a[:, 1, 2] - a[:, 2, 1]
    pair[:, 0, 2] = pair[:, 2, 0] = a[:, 2, 0] - a[:, 0, 2]
    pair[:, 0, 3] = pair[:, 3, 0] = a[:, 0, 1] - a[:, 1, 0]
    pair[:, 1, 2] = pair[:, 2, 1] = a[:, 0, 1] + a[:, 1, 0]
    pair[:, 1, 3] = pair[:, 3, 1] = a[:, 0, 2] + a[:, 2, 0]
    pair[:, 2, 3] = pair[:, 3, 2] = a[:, 1, 2] + a[:, 2, 1]
    idx = np.arange(4)
    pair[:, idx, idx] = four_sq
    finite = np.all(np.isfinite(four_sq), axis=1)
    best = np.argmax(np.where(finite[:, None], four_sq, 0.0), axis=1)
    rows = pair[np.arange(a.shape[0]), best]  # 4 q_best q_j for j = 0..3
    with np.errstate(invalid="ignore", divide="ignore"):
        q = rows / (2.0 * np.sqrt(np.take_along_axis(four_sq, best[:, None], axis=1)))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(q[:, :1] < 0, -q, q)
    q[~finite] = np.nan
    return q.reshape(np.shape(c)[:-2] + (4,))


def boresight_radec_roll(c: np.ndarray) -> tuple[float, float, float]:
    """Boresight (ra, dec) [deg] and roll [deg] of the attitude ``c`` (b = C r): the sensor's +z axis in the
    reference frame, and the angle from the image's -y axis (up) to the celestial north projected into the image,
    measured toward +x (NaN at a celestial pole, where north has no direction)."""
    c = np.asarray(c, dtype=np.float64)
    bore = c[2]
    ra, dec = unit_to_radec(bore[None, :])
    north = np.array([0.0, 0.0, 1.0]) - bore * bore[2]
    n_cam = c @ north
    roll = math.degrees(math.atan2(n_cam[0], -n_cam[1])) if np.hypot(n_cam[0], n_cam[1]) > 1e-12 else math.nan
    return math.degrees(float(ra[0])), math.degrees(float(dec[0])), roll


# ---------------------------------------------------------------------------------------------------------------
# FITS WCS: TAN (gnomonic) with SIP distortion (Shupe et al. 2005, "The SIP convention for representing distortion
# in FITS image headers"; Calabretta & Greisen 2002, FITS WCS paper II, TAN)

#: Grid points per detector side on which the SIP polynomials are checked (forward) and fitted (inverse).
SIP_GRID = 41
#: Order of the inverse polynomials AP, BP (world -> pixel): the inverse of Weng's model is not a polynomial; order
#: 7 keeps its fit error on a 1024 px detector with a few pixels of distortion below 1e-6 px (stated per file).
SIP_INVERSE_ORDER = 7


@dataclass(frozen=True)
class SipModel:
    """The calibrated camera's distortion in SIP form: ``a``/``b`` map (p, q) -> the coefficient of u^p v^q of the
    forward polynomials (pixel offset from CRPIX -> added to reach the ideal offset), ``ap``/``bp`` the fitted
    inverse ones; the largest errors [px] of each, on a grid over the detector (forward at its nodes, inverse at the
    midpoints between the nodes it was fitted on)."""

    order: int
    a: dict[tuple[int, int], float]
    b: dict[tuple[int, int], float]
    inverse_order: int
    ap: dict[tuple[int, int], float]
    bp: dict[tuple[int, int], float]
    forward_error_px: float
    inverse_error_px: float


def weng_as_sip(theta: np.ndarray) -> tuple[int, dict, dict]:
    """The Weng distortion of the model vector ``theta`` (docs/camera-model.md; seed 000 eq. 7) as SIP forward
    polynomials (order, A, B). Weng's dx, dy are polynomials in the measured offsets (u, v) of degree 2 (decentering
    and thin prism) and 3, 5, 7 (radial: u (k1 r^2 + k2 r^4 + k3 r^6), r^2n expanded binomially), and the ideal
    offset is u - dx while SIP adds A: so A = -dx and B = -dy term by term, exactly."""
    k1, k2, k3, p1, p2, s1, s2 = (float(theta[i]) for i in range(3, 10))
    g1, g2, g3, g4 = s1 + p1, s2 + p2, 2 * p1, 2 * p2
    dx = {(2, 0): g1 + g3, (1, 1): g4, (0, 2): g1}
    dy = {(2, 0): g2, (1, 1): g3, (0, 2): g2 + g4}
    for n, k in ((1, k1), (2, k2), (3, k3)):  # u r^2n and v r^2n, r^2n = sum_j C(n, j) u^2j v^2(n-j)
        for j in range(n + 1):
            dx[(2 * j + 1, 2 * (n - j))] = dx.get((2 * j + 1, 2 * (n - j)), 0.0) + k * comb(n, j)
            dy[(2 * j, 2 * (n - j) + 1)] = dy.get((2 * j, 2 * (n - j) + 1), 0.0) + k * comb(n, j)
    a = {pq: -v for pq, v in dx.items() if v != 0.0}
    b = {pq: -v for pq, v in dy.items() if v != 0.0}
    order = max([2] + [p + q for p, q in (*a, *b)])
    return order, a, b


def _poly(coeffs: dict[tuple[int, int], float], u: np.ndarray, v: np.ndarray) -> np.ndarray:
    out = np.zeros(np.broadcast_shapes(np.shape(u), np.shape(v)))
    for (p, q), c in coeffs.items():
        out += c * u**p * v**q
    return out


def _grid(image_size_px: tuple[int, int], principal_px: tuple[float, float], n: int, midpoints: bool):
    """Offsets (u, v) from the principal point of an n x n grid over the detector's extent (or its cell midpoints)."""
    w, h = image_size_px
    xs = np.linspace(-0.5, w - 0.5, n)
    ys = np.linspace(-0.5, h - 0.5, n)
    if midpoints:
        xs, ys = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (ys[1:] + ys[:-1])
    x, y = np.meshgrid(xs, ys)
    return x.ravel() - principal_px[0], y.ravel() - principal_px[1]


def sip_model(theta: np.ndarray, image_size_px: tuple[int, int]) -> SipModel:
    """The calibrated camera ``theta`` (model vector) in SIP form (:class:`SipModel`): the forward polynomials
    exactly (:func:`weng_as_sip`), their error checked against :func:`onboard.camera.distortion_px` on a
    :data:`SIP_GRID` grid; the inverse of order :data:`SIP_INVERSE_ORDER` fitted by least squares (monomials of
    degree 1..order in offsets scaled by the half-diagonal, for conditioning) on that grid and checked between its
    nodes."""
    theta = np.asarray(theta, dtype=np.float64)
    principal = (float(theta[1]), float(theta[2]))
    order, a, b = weng_as_sip(theta)
    u, v = _grid(image_size_px, principal, SIP_GRID, midpoints=False)
    dx, dy = distortion_px(u, v, theta)
    forward_err = float(np.max(np.hypot(_poly(a, u, v) + dx, _poly(b, u, v) + dy), initial=0.0))
    # inverse: at the ideal offsets U = u - dx, V = v - dy, AP(U, V) = u - U = dx and BP = dy
    big_u, big_v = u - dx, v - dy
    scale = 0.5 * math.hypot(*image_size_px)
    terms = [(p, d - p) for d in range(1, SIP_INVERSE_ORDER + 1) for p in range(d, -1, -1)]
    design = np.stack([(big_u / scale) ** p * (big_v / scale) ** q for p, q in terms], axis=1)
    sol, *_ = np.linalg.lstsq(design, np.stack([dx, dy], axis=1), rcond=None)
    ap = {pq: float(sol[k, 0]) / scale ** sum(pq) for k, pq in enumerate(terms)}
    bp = {pq: float(sol[k, 1]) / scale ** sum(pq) for k, pq in enumerate(terms)}
    um, vm = _grid(image_size_px, principal, SIP_GRID, midpoints=True)
    dxm, dym = distortion_px(um, vm, theta)
    big_um, big_vm = um - dxm, vm - dym
    inverse_err = float(
        np.max(np.hypot(big_um + _poly(ap, big_um, big_vm) - um, big_vm + _poly(bp, big_um, big_vm) - vm), initial=0)
    )
    return SipModel(order, a, b, SIP_INVERSE_ORDER, ap, bp, forward_err, inverse_err)


def tan_sip_cards(c: np.ndarray, theta: np.ndarray, sip: SipModel) -> list[tuple[str, object, str]]:
    """FITS WCS cards (keyword, value, comment) of one attitude ``c`` through the camera ``theta``: TAN at the
    boresight with SIP distortion (:func:`sip_model`), pixel coordinates as FITS counts them (the first pixel's
    centre is 1, so CRPIX = principal point + 1). The CD matrix is exact: a direction with ideal offsets (u', v')
    has standard coordinates xi = (u' (C e)_x + v' (C e)_y) / F, eta = (u' (C n)_x + v' (C n)_y) / F, with e and n
    the unit vectors east and north at the boresight (Calabretta & Greisen 2002, TAN with LONPOLE 180), since
    r . boresight = F / |(u', v', F)| for r = C^T b."""
    c = np.asarray(c, dtype=np.float64)
    ra0, dec0, _ = boresight_radec_roll(c)
    a0, d0 = math.radians(ra0), math.radians(dec0)
    east = np.array([-math.sin(a0), math.cos(a0), 0.0])
    north = np.array([-math.sin(d0) * math.cos(a0), -math.sin(d0) * math.sin(a0), math.cos(d0)])
    ce, cn = c @ east, c @ north
    deg_per_px = math.degrees(1.0) / float(theta[0])
    cards: list[tuple[str, object, str]] = [
        ("WCSAXES", 2, "two image axes"),
        ("CTYPE1", "RA---TAN-SIP", "TAN with SIP distortion"),
        ("CTYPE2", "DEC--TAN-SIP", "TAN with SIP distortion"),
        ("CUNIT1", "deg", ""),
        ("CUNIT2", "deg", ""),
        ("CRPIX1", float(theta[1]) + 1.0, "x0 + 1 (FITS pixels count from 1)"),
        ("CRPIX2", float(theta[2]) + 1.0, "principal point y0 + 1"),
        ("CRVAL1", ra0, "[deg] boresight right ascension"),
        ("CRVAL2", dec0, "[deg] boresight declination"),
        ("LONPOLE", 180.0, "[deg] native longitude of the celestial pole"),
        ("CD1_1", deg_per_px * float(ce[0]), "[deg/px]"),
        ("CD1_2", deg_per_px * float(ce[1]), "[deg/px]"),
        ("CD2_1", deg_per_px * float(cn[0]), "[deg/px]"),
        ("CD2_2", deg_per_px * float(cn[1]), "[deg/px]"),
        ("A_ORDER", sip.order, "SIP forward order (Weng model, exact)"),
    ]
    cards += [(f"A_{p}_{q}", v, "") for (p, q), v in sorted(sip.a.items())]
    cards.append(("B_ORDER", sip.order, ""))
    cards += [(f"B_{p}_{q}", v, "") for (p, q), v in sorted(sip.b.items())]
    cards.append(("AP_ORDER", sip.inverse_order, "SIP inverse order (least-squares fit)"))
    cards += [(f"AP_{p}_{q}", v, "") for (p, q), v in sorted(sip.ap.items())]
    cards.append(("BP_ORDER", sip.inverse_order, ""))
    cards += [(f"BP_{p}_{q}", v, "") for (p, q), v in sorted(sip.bp.items())]
    return cards
