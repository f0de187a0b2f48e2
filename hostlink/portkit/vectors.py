"""Golden test vectors from the onboard reference model, for proving a C port against it (``hostlink vectors DIR``).

For each function a port needs (pixel to direction, the camera Jacobians, the interstar residual and its Jacobian,
one U-D update, refraction by addition, apparent place, attitude, bank record encode/verify), one language-neutral
JSON file per precision: ``NAME.float32.json`` and, where the sensor without an FPU runs it in integers,
``NAME.fixed.json`` (``bank_record.bytes.json`` is byte-exact and precision-free). Each file holds the inputs and
the reference outputs of a few cases, exact to the bit, and for every output the tolerance a port must meet and why.

Encoding (docs/port-kit.md): an array is ``{"dtype", "shape", ...}`` in C (row-major) order; float32 and float64
values are their IEEE-754 bit patterns in hexadecimal (``"hex"``: ``"3f800000"`` is 1.0f; exact, NaN payloads
included) with a decimal ``"value"`` for reading only; integers (fixed point, counts, indices) are decimal strings
in ``"value"`` (int64 does not survive every JSON parser as a number); bytes are one hex string.

Tolerances (``"tolerance"``: per output, ``abs`` in the output's units, a number or an array broadcast against the
output, and ``why``):

* float32: derived from the format's error bound, never fitted to a measurement. With u = 2^-24 (float32's unit
  roundoff) and gamma_n = n u / (1 - n u) the worst-case relative error of n dependent operations (Higham 2002,
  *Accuracy and Stability of Numerical Algorithms*, Lemma 3.1), each output's bound is gamma_n times the magnitude
  that the n operations act on, with n counted from the code (:mod:`hostlink.portkit.costs`). A port that evaluates
  in another order, contracts to FMA, or uses another libm (sinf, sqrtf are faithful to 1 ulp) stays within it;
  a wrong term, sign, coefficient or index does not.
* fixed point: 0 (bit-exact). The integer formats round by one stated rule (``rshift_round``: add 2^(n-1), shift
  right arithmetically), so a correct port reproduces every bit; anything else is a bug.
* bytes: exact.

``check_vectors`` (the test) regenerates every output with the Python model from the stored inputs and compares
within the tolerance, and also evaluates the float32 functions in float64 (the same code) and the fixed-point ones
against the float64 camera model, so each tolerance is shown to hold for the reference itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from onboard import apparent, attitude, banks, camera, earth, fixedpoint, interstar, refraction, ud
from onboard.params import CameraParams, Distortion
from onboard.site import Weather
from onboard.timescale import from_calendar, make_time

#: float32 unit roundoff.
U32 = 2.0**-24
#: Version of the vector file layout.
FORMAT_VERSION = 1


def gamma(n: int, u: float = U32) -> float:
    """gamma_n = n u / (1 - n u): the worst-case relative error of n floating-point operations (Higham 2002,
    Lemma 3.1)."""
    return n * u / (1.0 - n * u)


def ulp32(x: float) -> float:
    """Spacing of float32 numbers at |x| [same unit as x]."""
    return float(np.spacing(np.float32(abs(x))))


# ----------------------------------------------------------------------------------------------- array codec
def encode_array(a) -> dict:
    """An array (or scalar) -> its JSON object (module docstring)."""
    if isinstance(a, (bytes, bytearray)):
        return {"dtype": "bytes", "hex": bytes(a).hex()}
    arr = np.asarray(a)
    out: dict = {"dtype": str(arr.dtype), "shape": list(arr.shape)}
    flat = arr.reshape(-1)
    if arr.dtype == np.float32:
        out["hex"] = [f"{int(v):08x}" for v in flat.view(np.uint32)]
    elif arr.dtype == np.float64:
        out["hex"] = [f"{int(v):016x}" for v in flat.view(np.uint64)]
    elif arr.dtype == np.bool_:
        out["dtype"] = "bool"
        out["value"] = [bool(v) for v in flat]
        return out
    else:
        out["value"] = [str(int(v)) for v in flat]
        return out
    out["value"] = [None if not math.isfinite(float(v)) else float(v) for v in flat]
    return out


def decode_array(obj: dict):
    """Inverse of :func:`encode_array`: bytes, or a numpy array of the stored dtype and shape."""
    dtype = obj["dtype"]
    if dtype == "bytes":
        return bytes.fromhex(obj["hex"])
    shape = tuple(obj["shape"])
    if dtype == "float32":
        return np.array([int(h, 16) for h in obj["hex"]], dtype=np.uint32).view(np.float32).reshape(shape)
    if dtype == "float64":
        return np.array([int(h, 16) for h in obj["hex"]], dtype=np.uint64).view(np.float64).reshape(shape)
    if dtype == "bool":
        return np.array(obj["value"], dtype=bool).reshape(shape)
    return np.array([int(v) for v in obj["value"]], dtype=dtype).reshape(shape)


# ------------------------------------------------------------------------------------------------ test inputs
def vector_camera() -> CameraParams:
    """The camera of the vectors: seed 004's 1024 x 1024 px, 12 um, 70 mm design with its measured radial
    distortion, plus decentering and thin prism, so that every term of the model is exercised."""
    return CameraParams(
        focal_length_mm=70.2262,
        pixel_pitch_um=12.0,
        principal_point_px=(500.0, 530.0),
        image_size_px=(1024, 1024),
        distortion=Distortion(k1=-2e-10, k2=3.5e-15, k3=-1e-20, p1=2e-7, p2=-1.5e-7, s1=1e-7, s2=-5e-8),
    )


def _centroids(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n centroids on the 2^-10 px wire grid (as they arrive), corners and edges included."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 1023.5, n)
    y = rng.uniform(-0.5, 1023.5, n)
    x[:4] = (-0.5, 1023.5, -0.5, 1023.5)
    y[:4] = (-0.5, -0.5, 1023.5, 1023.5)
    return np.rint(x * 1024) / 1024, np.rint(y * 1024) / 1024


def _catalogue_directions(b: np.ndarray, seed: int) -> np.ndarray:
    """Reference directions r = C^T b for a random attitude C (float64, unit)."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c = q * np.sign(np.linalg.det(q))
    return b @ c


# ------------------------------------------------------------------------------------------------- the specs
@dataclass(frozen=True)
class Tolerance:
    """Allowed |port - reference| for one output: ``abs`` (a number, or an array broadcast against the output) and
    the reason."""

    abs: float | np.ndarray
    why: str

    def as_json(self) -> dict:
        a = np.asarray(self.abs, dtype=np.float64)
        return {"abs": float(a) if a.ndim == 0 else encode_array(a), "why": self.why}


@dataclass(frozen=True)
class VectorSpec:
    """One vector file: a function in one precision, how to build its cases, compute its outputs in a dtype (the
    same code in float32 and float64), and bound them."""

    name: str
    precision: str  # "float32", "fixed" or "bytes"
    reference: str  # the onboard function(s) the vectors come from
    description: str
    cases: Callable[[], list[dict]]
    compute: Callable[[dict, type], dict]
    tolerance: Callable[[dict, dict], dict[str, Tolerance]]
    #: constants of the algorithm a port must hold (tables, iteration counts), written once per file
    constants: Callable[[], dict] | None = None

    @property
    def file_name(self) -> str:
        return f"{self.name}.{self.precision}.json"


# pixel to direction -----------------------------------------------------------------------------------
def _p2d_cases() -> list[dict]:
    theta = vector_camera().model_vector(np.float32)
    out = []
    for seed, n in ((1, 24), (2, 8)):
        x, y = _centroids(n, seed)
        out.append({"theta": theta, "x_px": x.astype(np.float32), "y_px": y.astype(np.float32)})
    return out


def _p2d_compute(inp: dict, dtype) -> dict:
    theta, x, y = (np.asarray(inp[k]).astype(dtype) for k in ("theta", "x_px", "y_px"))
    u_i, v_i = camera.ideal_offsets(x, y, theta)
    return {"u_ideal_px": u_i, "v_ideal_px": v_i, "b": camera.offsets_to_unit(u_i, v_i, theta[0])}


def _p2d_uv_tolerance(inp: dict, out: dict) -> float:
    x = np.asarray(inp["x_px"], np.float64)
    theta = np.asarray(inp["theta"], np.float64)
    u = np.abs(x - theta[1])
    dx, _ = camera.distortion_px(u, u, theta)
    # u - dx, with dx evaluated in any order: 2 ulp of |u'| (the final subtraction may round either way once dx
    # differs) plus gamma_16 of the distortion terms (16 operations from u, v to dx; |dx| < 1 px here)
    return 2 * ulp32(float(np.max(np.abs(out["u_ideal_px"])))) + gamma(16) * float(np.max(np.abs(dx)) + 1.0)


def _p2d_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    tol_uv = _p2d_uv_tolerance(inp, out)
    f_px = float(inp["theta"][0])
    why_uv = (
        "2 ulp of float32 at the largest |u'| (the last subtraction u - dx may round either way) + gamma_16 of "
        "|dx| + 1 px (the 16 operations of the Weng terms, evaluated in any order)"
    )
    why_b = (
        "gamma_8 on components of magnitude <= 1 (w.w: 5 operations, sqrt, divide, and one rounding of the "
        "result) + the u', v' tolerance divided by F (the direction moves by du / F)"
    )
    return {
        "u_ideal_px": Tolerance(tol_uv, why_uv),
        "v_ideal_px": Tolerance(tol_uv, why_uv),
        "b": Tolerance(gamma(8) + tol_uv / f_px, why_b),
    }


def _p2d_fixed_cases() -> list[dict]:
    out = []
    for case in _p2d_cases():
        cam = fixedpoint.fixed_camera(case["theta"], vector_camera().image_size_px)
        x_steps = np.rint(case["x_px"].astype(np.float64) * 1024).astype(np.int64)
        y_steps = np.rint(case["y_px"].astype(np.float64) * 1024).astype(np.int64)
        out.append(
            {
                "theta": case["theta"],
                "image_size_px": np.array(cam.image_size_px, dtype=np.int64),
                "x_q10": x_steps,
                "y_q10": y_steps,
            }
        )
    return out


def _fixed_camera_outputs(cam: fixedpoint.FixedCamera) -> dict:
    return {
        "s": np.array(cam.s, dtype=np.int64),
        "x0_q": np.array(cam.x0_q, dtype=np.int64),
        "y0_q": np.array(cam.y0_q, dtype=np.int64),
        "coef_m": np.array(cam.coef_m, dtype=np.int64),
        "coef_e": np.array(cam.coef_e, dtype=np.int64),
        "qw": np.array(cam.qw, dtype=np.int64),
        "f_w": np.array(cam.f_w, dtype=np.int64),
        "theta_q": np.asarray(cam.theta_q, dtype=np.float64),
    }


def _front_end_constants() -> dict:
    """The fixed-point front end's constants: the reciprocal-square-root table (Q30, bins a >> 26 from the first
    bin on) and its Newton iterations, the fractional bits of the formats (onboard/fixedpoint.py)."""
    return {
        "rsqrt_table_q30": np.asarray(fixedpoint.RSQRT_TABLE, dtype=np.int64),
        "rsqrt_table_first_bin": np.array(fixedpoint.RSQRT_TABLE_FIRST, dtype=np.int64),
        "rsqrt_iterations": np.array(fixedpoint.RSQRT_ITERATIONS, dtype=np.int64),
        "q": np.array(fixedpoint.Q, dtype=np.int64),
        "centroid_frac_bits": np.array(fixedpoint.CENTROID_FRAC_BITS, dtype=np.int64),
        "e_frac_bits": np.array(fixedpoint.E_FRAC_BITS, dtype=np.int64),
    }


def _p2d_fixed_compute(inp: dict, dtype) -> dict:
    cam = fixedpoint.fixed_camera(inp["theta"], tuple(int(v) for v in inp["image_size_px"]))
    u_i, v_i = fixedpoint.ideal_offsets_q30(inp["x_q10"], inp["y_q10"], cam)
    b = fixedpoint.offsets_to_unit_q30(u_i, v_i, cam)
    return {**_fixed_camera_outputs(cam), "u_ideal_q30": u_i, "v_ideal_q30": v_i, "b_q30": b}


_EXACT = "integer arithmetic with one stated rounding rule (rshift_round): a correct port is bit-exact"


def _exact(names) -> Callable[[dict, dict], dict[str, Tolerance]]:
    def tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
        return {k: Tolerance(0.0, _EXACT) for k in names}

    return tolerance


def _p2d_fixed_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    tol = _exact(out)(inp, out)
    tol["theta_q"] = Tolerance(0.0, "the float64 value the integers represent: exact (powers-of-two scalings)")
    return tol


# camera Jacobians ------------------------------------------------------------------------------------------
def _jac_compute(inp: dict, dtype) -> dict:
    theta, x, y = (np.asarray(inp[k]).astype(dtype) for k in ("theta", "x_px", "y_px"))
    b, j_theta, j_centroid = camera.unit_vector_jacobians(x, y, theta)
    return {"b": b, "j_theta": j_theta, "j_centroid": j_centroid}


def _jac_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    # b = w / |w|, J = P Jw with P = (I - b b^T) / |w|: the error of each product is gamma_n of sum_m |P_cm| |Jw_mk|,
    # evaluated here in float64 per (star, component, column), and bounded per column (columns differ by decades)
    theta, x, y = (np.asarray(inp[k], np.float64) for k in ("theta", "x_px", "y_px"))
    q, jq_theta, jq_centroid = camera.ideal_offset_jacobians(x, y, theta)
    w = np.concatenate([q, np.full((q.shape[0], 1), theta[0])], axis=1)
    norm = np.linalg.norm(w, axis=1)
    b = w / norm[:, None]
    # the rounding of I - b b^T is relative to I + |b| |b|^T (1 - b_z^2 cancels for a star near the boresight)
    proj = (np.eye(3)[None] + np.abs(b[:, :, None] * b[:, None, :])) / norm[:, None, None]
    jw = np.zeros((q.shape[0], 3, 10))
    jw[:, :2, :] = np.abs(jq_theta)
    jw[:, 2, 0] = 1.0
    scale_theta = np.max(proj @ jw, axis=(0, 1))
    scale_c = np.max(proj[:, :, :2] @ np.abs(jq_centroid), axis=(0, 1))
    n = 24
    why = (
        f"gamma_{n} of max over stars of sum_m |P_cm| |Jw_mk| per column, with |P| = (I + |b| |b|^T) / |w| (the "
        "magnitudes that the projector (I - b b^T) / |w| is computed from) and Jw the Jacobian of w = (u', v', F): "
        "about 14 dependent operations for Jw, 5 for P, 5 for the product"
    )
    return {
        "b": _p2d_tolerance(inp, _p2d_compute(inp, np.float32))["b"],
        "j_theta": Tolerance(gamma(n) * scale_theta, why),
        "j_centroid": Tolerance(gamma(n) * scale_c, why),
    }


# interstar residual and Jacobian -----------------------------------------------------------------------------
def _interstar_cases() -> list[dict]:
    out = []
    for case in _p2d_cases():
        theta = case["theta"]
        b64 = camera.pixels_to_unit(
            case["x_px"].astype(np.float64), case["y_px"].astype(np.float64), theta.astype(np.float64)
        )
        r = _catalogue_directions(b64, 7).astype(np.float32)
        b, jb, _ = camera.unit_vector_jacobians(case["x_px"], case["y_px"], theta)
        order = interstar.order_for_pairs(case["x_px"], case["y_px"])
        i, j = interstar.independent_pairs(b.shape[0])
        out.append(
            {
                "b": b[order],
                "r": r[order],
                "jb": jb[order],
                "pair_i": i.astype(np.int32),
                "pair_j": j.astype(np.int32),
            }
        )
    return out


def _interstar_compute(inp: dict, dtype) -> dict:
    b, r, jb = (np.asarray(inp[k]).astype(dtype) for k in ("b", "r", "jb"))
    i, j = inp["pair_i"], inp["pair_j"]
    return {"e": interstar.difference_residuals(b, r, i, j), "h": interstar.difference_jacobian(b, jb, i, j)}


def _interstar_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    b, r, jb = (np.asarray(inp[k], np.float64) for k in ("b", "r", "jb"))
    i, j = inp["pair_i"], inp["pair_j"]
    db, dr = b[i] - b[j], r[i] - r[j]
    scale_e = float(np.max(np.sum(db * db, axis=1) + np.sum(dr * dr, axis=1))) / 2
    # per column: sum_c |d_c| (|J_ic| + |J_jc|)
    scale_h = np.max(np.einsum("pc,pck->pk", np.abs(db), np.abs(jb[i]) + np.abs(jb[j])), axis=0)
    return {
        "e": Tolerance(
            gamma(7) * scale_e,
            "gamma_7 of (|b_i - b_j|^2 + |r_i - r_j|^2) / 2: a difference, 3 squares and 2 additions per norm, "
            "their difference (the halving is exact)",
        ),
        "h": Tolerance(
            gamma(5) * scale_h,
            "gamma_5 of sum_c |b_i - b_j|_c (|J_i| + |J_j|)_c per column: two differences, 3 products, 2 additions",
        ),
    }


def _interstar_fixed_cases() -> list[dict]:
    out = []
    for case in _p2d_fixed_cases():
        cam = fixedpoint.fixed_camera(case["theta"], (1024, 1024))
        b_q30 = fixedpoint.pixels_to_unit_q30(case["x_q10"], case["y_q10"], cam)
        r = _catalogue_directions(b_q30 * 2.0**-30, 7)
        i, j = interstar.independent_pairs(b_q30.shape[0])
        out.append({"b_q30": b_q30, "r_q30": fixedpoint.quantise_unit_q30(r), "pair_i": i, "pair_j": j})
    return out


def _interstar_fixed_compute(inp: dict, dtype) -> dict:
    return {"e_q61": fixedpoint.difference_residuals_q61(inp["b_q30"], inp["r_q30"], inp["pair_i"], inp["pair_j"])}


# U-D update ----------------------------------------------------------------------------------------------------
def _ud_cases() -> list[dict]:
    out = []
    k = 10
    for seed in (1, 2, 3):
        rng = np.random.default_rng(100 + seed)
        u = np.triu(rng.normal(0, 0.3, (k, k)), 1) + np.eye(k)
        d = 10.0 ** rng.uniform(-3, 0, k)
        out.append(
            {
                "u": u.astype(np.float32),
                "d": d.astype(np.float32),
                "xi": rng.normal(0, 0.5, k).astype(np.float32),
                "h": rng.normal(0, 1, k).astype(np.float32),
                "y": np.array(rng.normal(0, 2), dtype=np.float32),
            }
        )
    return out


def _ud_compute(inp: dict, dtype) -> dict:
    u, d, xi, h = (np.array(inp[k], dtype=dtype) for k in ("u", "d", "xi", "h"))
    y = np.asarray(inp["y"]).astype(dtype)[()]
    innovation, s = ud.bierman_update(u, d, xi, h, y, ud.bierman_work(u.shape[0], np.dtype(dtype)))
    return {
        "u": u,
        "d": d,
        "xi": xi,
        "innovation": np.asarray(innovation, dtype=dtype),
        "innovation_variance": np.asarray(s, dtype=dtype),
    }


def _ud_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    k = np.shape(inp["u"])[0]
    n = 3 * k + 6
    u, d, h = (np.asarray(inp[x], np.float64) for x in ("u", "d", "h"))
    f = h @ u
    scale_s = 1.0 + float(np.sum(d * f * f))  # the positive sum alpha_K = h P h + 1 (no cancellation)
    scale_u = float(np.max(np.abs(u))) * (1.0 + float(np.max(np.abs(f)) * np.max(np.abs(d * f))))
    ref = _ud_compute(inp, np.float64)
    gain = np.abs(ref["xi"] - np.asarray(inp["xi"], np.float64))
    why = (
        f"gamma_{n} (n = 3K + 6: U^T h, the cumulative alpha and the cumulative column sums, K operations each, "
        "plus 6) of the magnitude the update acts on"
    )
    return {
        "u": Tolerance(gamma(n) * scale_u, why + ": max|U| (1 + max|f| max|D f|)"),
        "d": Tolerance(gamma(n) * np.abs(ref["d"]), why + ": relative to each d_j' (alpha > 0: no cancellation)"),
        "xi": Tolerance(
            gamma(n) * (np.abs(ref["xi"]) + gain + float(np.abs(ref["innovation"]))),
            why + ": |xi'| + |gain innovation| + |innovation|",
        ),
        "innovation": Tolerance(
            gamma(k + 1) * (abs(float(inp["y"])) + float(np.abs(h) @ np.abs(np.asarray(inp["xi"], np.float64)))),
            f"gamma_{k + 1} of |y| + |h| . |xi| (a dot product of K terms and one subtraction)",
        ),
        "innovation_variance": Tolerance(gamma(n) * scale_s, why + ": h P h + 1"),
    }


# refraction by addition --------------------------------------------------------------------------------------
def _refraction_cases() -> list[dict]:
    out = []
    for seed, weather in ((1, Weather(10.0, 1013.25, 0.5)), (2, Weather(-20.0, 750.0, 0.0))):
        rng = np.random.default_rng(200 + seed)
        zen = rng.normal(size=3)
        zen /= np.linalg.norm(zen)
        z = np.radians(np.concatenate([[0.0, 45.0, 75.0, 85.0, 89.0], rng.uniform(0, 80, 11)]))
        az = rng.uniform(0, 2 * np.pi, z.size)
        # directions at zenith distance z around the zenith
        e1 = np.cross(zen, [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(zen, e1)
        r = np.cos(z)[:, None] * zen + np.sin(z)[:, None] * (np.cos(az)[:, None] * e1 + np.sin(az)[:, None] * e2)
        a, b = refraction.refraction_coefficients(weather)
        out.append(
            {
                "r": r.astype(np.float32),
                "zenith": zen.astype(np.float32),
                "a_rad": np.array(a, dtype=np.float64),
                "b_rad": np.array(b, dtype=np.float64),
            }
        )
    return out


def _refraction_compute(inp: dict, dtype) -> dict:
    r = np.asarray(inp["r"]).astype(dtype)
    zenith = np.asarray(inp["zenith"]).astype(dtype)
    a, b = float(inp["a_rad"]), float(inp["b_rad"])
    cz, sz, tangential = refraction.zenith_geometry(r, zenith)
    refr = refraction.refraction_from_true_zenith(cz, sz, a, b)
    limit = np.dtype(dtype).type(a) / np.maximum(cz, np.dtype(dtype).type(refraction.MIN_COS_ZENITH))
    return {"refraction_rad": refr, "apparent": refraction.rotate_in_vertical(r, sz, tangential, refr, limit)}


def _refraction_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    ref = _refraction_compute(inp, np.float64)
    r, zen = np.asarray(inp["r"], np.float64), np.asarray(inp["zenith"], np.float64)
    cz = np.maximum(r @ zen, refraction.MIN_COS_ZENITH)
    sz = np.sqrt(np.maximum(1.0 - cz * cz, 0.0))
    # sin z = |U - (r.U) r| carries an absolute error of about 4u in its square: 4u / (2 sin z), at most 2 sqrt(u)
    # (a direction at the zenith gets a spurious sin z ~ sqrt(u)); R ~ A tan z turns it into A d(sin z) / cos^3 z
    d_sin = np.minimum(2 * U32 / np.maximum(sz, 1e-300), 2 * math.sqrt(U32))
    tol_r = (gamma(30) + 4 * U32 / cz) * np.abs(ref["refraction_rad"]) + abs(float(inp["a_rad"])) * d_sin / cz**3
    return {
        "refraction_rad": Tolerance(
            tol_r,
            "per direction: gamma_30 relative (2 Newton steps of about 15 operations) + 4 u / cos z (tan z = "
            "sin z / cos z amplifies the rounding of cos z, limited at cos z = 0.05) + A d(sin z) / cos^3 z with "
            "d(sin z) = min(2 u / sin z, 2 sqrt u), the error of sin z = |U - (r.U) r| near the zenith",
        ),
        "apparent": Tolerance(
            gamma(8) + float(np.max(tol_r)),
            "gamma_8 on unit components (the tangential vector U - (r.U) r, cos R r + sin R / sin z t) + the "
            "largest refraction tolerance (the direction turns by R)",
        ),
    }


# apparent place -------------------------------------------------------------------------------------------------
def _apparent_cases() -> list[dict]:
    rng = np.random.default_rng(300)
    n = 12
    ra = rng.uniform(0, 2 * np.pi, n)
    dec = np.arcsin(rng.uniform(-1, 1, n))
    r0, pm = apparent.catalogue_vectors(ra, dec, rng.normal(0, 200, n), rng.normal(0, 200, n), np.float32)
    plx = rng.uniform(0, 300, n).astype(np.float32)
    out = []
    for year, month in ((2026, 11), (2041, 3)):
        t = from_calendar(year, month, 23, 5, 30, 12_345_678)
        out.append(
            {
                "r0": r0,
                "pm_rad_yr": pm,
                "parallax_mas": plx,
                "epoch_jyear": np.array(apparent.EPOCH_HIPPARCOS_JYEAR, dtype=np.float64),
                "t_tt_day": np.asarray(t.day, dtype=np.int32),
                "t_tt_frac": np.asarray(t.frac, dtype=np.uint32),
            }
        )
    return out


def _apparent_compute(inp: dict, dtype) -> dict:
    t = make_time(inp["t_tt_day"], inp["t_tt_frac"])
    r0, pm, plx = (np.asarray(inp[k]).astype(dtype) for k in ("r0", "pm_rad_yr", "parallax_mas"))
    return {
        "tod_matrix": earth.true_of_date_matrix(t, dtype),
        "apparent": apparent.apparent_place_vectors(r0, pm, plx, float(inp["epoch_jyear"]), t),
    }


def _apparent_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    return {
        "tod_matrix": Tolerance(
            gamma(24),
            "gamma_24 on entries <= 1: four rotation matrices (each entry a sin or cos, faithful to 1 ulp, of an "
            "angle from a short polynomial) and their three 3 x 3 products (5 operations per entry each)",
        ),
        "apparent": Tolerance(
            gamma(32),
            "gamma_32 on unit components: the matrix (24, above), the product with the direction (5) and the "
            "normalisation (sum of squares, sqrt, divide); the corrections are < 1e-4 and add only relative error",
        ),
    }


_INSTANT_FIELDS = ("years_q20", "earth_bary_q30", "sun_to_earth_q30", "deflection_k_q70", "beta_q44", "tod_q30")


def _apparent_fixed_cases() -> list[dict]:
    """The float32 cases' catalogue in the fixed formats (r0 Q30, pm Q46, parallax Q48 rad) and each instant's
    quantities from ``apparent.fixed_instant`` (soft float64 once per frame on the sensor: inputs here)."""
    out = []
    for case in _apparent_cases():
        r0, pm, plx = apparent.fixed_catalogue(
            case["r0"].astype(np.float64), case["pm_rad_yr"].astype(np.float64), case["parallax_mas"]
        )
        inst = apparent.fixed_instant(make_time(case["t_tt_day"], case["t_tt_frac"]), float(case["epoch_jyear"]))
        fields = {k: np.asarray(getattr(inst, k), dtype=np.int64) for k in _INSTANT_FIELDS}
        out.append({"r0_q30": r0, "pm_q46": pm, "parallax_q48": plx} | fields)
    return out


def _apparent_fixed_constants() -> dict:
    """Fractional bits of the formats and the Sun clamp (onboard/apparent.py); the reciprocal-square-root table of
    the normalisation is in pixel_to_direction.fixed.json."""
    bits = ("PM", "YEARS", "PARALLAX", "CHANGE", "DEFLECTION_K", "ABERRATION_BETA")
    return {f"{b.lower()}_frac_bits": np.array(getattr(apparent, f"{b}_FRAC_BITS"), dtype=np.int64) for b in bits} | {
        "min_one_plus_pe_q30": np.array(apparent.MIN_ONE_PLUS_PE_Q30, dtype=np.int64)
    }


def _apparent_fixed_compute(inp: dict, dtype) -> dict:
    inst = apparent.FixedInstant(
        **{k: int(inp[k]) if np.ndim(inp[k]) == 0 else np.asarray(inp[k]) for k in _INSTANT_FIELDS}
    )
    return {
        "apparent_q30": apparent.apparent_place_vectors_q30(inp["r0_q30"], inp["pm_q46"], inp["parallax_q48"], inst)
    }


# attitude ------------------------------------------------------------------------------------------------------
def _attitude_cases() -> list[dict]:
    out = []
    for seed, n in ((1, 24), (2, 5)):
        x, y = _centroids(n, seed + 10)
        b = camera.pixels_to_unit(x, y, vector_camera().model_vector())
        r = _catalogue_directions(b, seed + 20)
        w = np.random.default_rng(seed).uniform(0.5, 2.0, n)
        out.append({"b": b.astype(np.float32), "r": r.astype(np.float32), "weights": w.astype(np.float32)})
    return out


def _attitude_compute(inp: dict, dtype) -> dict:
    b, r, w = (np.asarray(inp[k]).astype(dtype) for k in ("b", "r", "weights"))
    return {"c": attitude.attitude_from_vectors(b, r, w)}


def _attitude_tolerance(inp: dict, out: dict) -> dict[str, Tolerance]:
    b = np.asarray(inp["b"], np.float64)
    spread = float(np.sqrt(np.mean(np.sum((b - b.mean(axis=0)) ** 2, axis=1))))
    return {
        "c": Tolerance(
            gamma(8) + 4 * U32 / spread,
            "gamma_8 on entries <= 1 (the refinement's small rotation and its product) + 4 u / rho, rho the RMS "
            "spread of the directions [rad]: the float32 floor of the inputs (u per component) seen through a "
            "field of that size (the rotation about the boresight is determined by the spread alone)",
        )
    }


# bank records --------------------------------------------------------------------------------------------------
def _bank_cases() -> list[dict]:
    table = banks.params_to_table(vector_camera(), np.array([0.05, 2.0, 2.0, 1e-10, 1e-15, np.nan, 0, 0, 0, 0]))
    epoch = 0x5EED0001
    good = banks.encode_bank_record(banks.BankRecord(seq=7, generation=3, nonce_counter=41, table=table, epoch=epoch))
    flipped = bytearray(good)
    flipped[50] ^= 0x04
    half = bytearray(good)
    half[96:] = b"\xff" * (len(good) - 96)  # a program cut after 96 bytes
    stage = banks.encode_stage_record(42, epoch)
    return [
        {
            "seq": np.array(7, np.uint32),
            "generation": np.array(3, np.uint32),
            "nonce_counter": np.array(41, np.uint32),
            "epoch": np.array(epoch, np.uint32),
            "table": table,
            "stage_counter": np.array(42, np.uint32),
            "verify_records": good + bytes(flipped) + bytes(half) + b"\xff" * len(good),
            "verify_stage_records": stage + stage[:4] + bytes([stage[4] ^ 1]) + stage[5:] + b"\xff" * len(stage),
        }
    ]


def _bank_compute(inp: dict, dtype) -> dict:
    rec = banks.BankRecord(
        int(inp["seq"]), int(inp["generation"]), int(inp["nonce_counter"]), inp["table"], int(inp["epoch"])
    )
    encoded = banks.encode_bank_record(rec)
    size = banks.BANK_RECORD_BYTES
    blobs = inp["verify_records"]
    decoded = [banks.decode_bank_record(blobs[k : k + size]) for k in range(0, len(blobs), size)]
    stages = inp["verify_stage_records"]
    ssize = banks.STAGE_RECORD_BYTES
    counters = [banks.decode_stage_record(stages[k : k + ssize]) for k in range(0, len(stages), ssize)]
    return {
        "bank_record": encoded,
        "record_crc32": np.array(int.from_bytes(encoded[-4:], "little"), np.uint32),
        "stage_record": banks.encode_stage_record(int(inp["stage_counter"]), int(inp["epoch"])),
        "verify_valid": np.array([d is not None for d in decoded]),
        "verify_generation": np.array([d.generation if d else 0 for d in decoded], np.uint32),
        "verify_stage_counter": np.array([n[0] if n is not None else 0 for n in counters], np.uint32),
        "verify_stage_valid": np.array([n is not None for n in counters]),
    }


def _bytes_exact(inp: dict, out: dict) -> dict[str, Tolerance]:
    return {k: Tolerance(0.0, "bytes and verdicts: exact") for k in out}


def _refraction_fixed_cases() -> list[dict]:
    """The float32 cases in the fixed formats (r, zenith Q30; A, B Q56), each with no site velocity (refraction
    alone) and with a 420 m/s one (beta Q48: diurnal aberration first)."""
    out = []
    for case in _refraction_cases():
        coef = (round(float(case[k]) * 2.0**refraction.COEF_FRAC_BITS) for k in ("a_rad", "b_rad"))
        base = {
            "r_q30": fixedpoint.quantise_unit_q30(case["r"].astype(np.float64)),
            "zenith_q30": fixedpoint.quantise_unit_q30(case["zenith"].astype(np.float64)),
            "ab_q56": np.array(list(coef), dtype=np.int64),
        }
        for velocity in ((0.0, 0.0, 0.0), (210.0, -340.0, 120.0)):
            out.append(base | {"beta_q48": refraction.beta_q48(np.array(velocity))})
    return out


def _refraction_fixed_compute(inp: dict, dtype) -> dict:
    coef = refraction.FixedRefraction(int(inp["ab_q56"][0]), int(inp["ab_q56"][1]))
    args = (inp["r_q30"], inp["zenith_q30"], inp["beta_q48"])
    return {
        "aberrated_q30": refraction.topocentric_observed_q30(*args, None),
        "observed_q30": refraction.topocentric_observed_q30(*args, coef),
    }


def _refraction_fixed_constants() -> dict:
    """Fractional bits of the formats, the Newton steps and the horizon clamp (onboard/refraction.py)."""
    return {
        "q": np.array(fixedpoint.Q, dtype=np.int64),
        "beta_frac_bits": np.array(refraction.BETA_FRAC_BITS, dtype=np.int64),
        "coef_frac_bits": np.array(refraction.COEF_FRAC_BITS, dtype=np.int64),
        "r_frac_bits": np.array(refraction.R_FRAC_BITS, dtype=np.int64),
        "tan_frac_bits": np.array(refraction.TAN_FRAC_BITS, dtype=np.int64),
        "tan2_frac_bits": np.array(refraction.TAN2_FRAC_BITS, dtype=np.int64),
        "newton_steps": np.array(refraction.TRUE_ZENITH_NEWTON_STEPS, dtype=np.int64),
        "min_cos_zenith_q30": np.array(round(refraction.MIN_COS_ZENITH * 2**fixedpoint.Q), dtype=np.int64),
        "isqrt_iterations": np.array(fixedpoint.ISQRT_ITERATIONS, dtype=np.int64),
    }


# ------------------------------------------------------------------------------------------------------ table
def _jac_cases() -> list[dict]:
    return [_p2d_cases()[1]]


SPECS: tuple[VectorSpec, ...] = (
    VectorSpec(
        "pixel_to_direction",
        "float32",
        "onboard.camera.ideal_offsets, onboard.camera.offsets_to_unit (= pixels_to_unit)",
        "Measured centroid [px] -> ideal offsets u', v' [px] -> sensor-frame unit vector b (docs/camera-model.md, seed "
        "000 eq. 7). theta = (F px, x0, y0, k1, k2, k3, p1, p2, s1, s2).",
        _p2d_cases,
        _p2d_compute,
        _p2d_tolerance,
    ),
    VectorSpec(
        "pixel_to_direction",
        "fixed",
        "onboard.fixedpoint.fixed_camera, ideal_offsets_q30, offsets_to_unit_q30",
        "The fixed-point front end: the float32 model vector -> the camera in block floating point (s, x0_q, "
        "y0_q, coef_m, coef_e, qw, f_w; once per linearisation), then Q10 centroids -> Q30 ideal offsets (px / 2^s) "
        "-> Q30 unit vectors.",
        _p2d_fixed_cases,
        _p2d_fixed_compute,
        _p2d_fixed_tolerance,
        _front_end_constants,
    ),
    VectorSpec(
        "camera_jacobians",
        "float32",
        "onboard.camera.unit_vector_jacobians",
        "Unit vectors and their Jacobians db/dtheta (N, 3, 10; F in px) and db/d(x, y) (N, 3, 2). A sensor "
        "without an FPU runs these in float32 (soft float): no fixed-point file.",
        _jac_cases,
        _jac_compute,
        _jac_tolerance,
    ),
    VectorSpec(
        "interstar_residual",
        "float32",
        "onboard.interstar.difference_residuals, difference_jacobian",
        "e_ij = (|b_i - b_j|^2 - |r_i - r_j|^2) / 2 over the 2N - 3 independent pairs (0,1), (0,k), (1,k) of the "
        "stars in pair order, and its Jacobian h = -(b_i - b_j)^T (J_i - J_j) (P, 10).",
        _interstar_cases,
        _interstar_compute,
        _interstar_tolerance,
    ),
    VectorSpec(
        "interstar_residual",
        "fixed",
        "onboard.fixedpoint.difference_residuals_q61",
        "The residuals from Q30 unit vectors, exact in Q61 (the Jacobian stays float32: see the float32 file).",
        _interstar_fixed_cases,
        _interstar_fixed_compute,
        _exact(("e_q61",)),
    ),
    VectorSpec(
        "ud_update",
        "float32",
        "onboard.ud.bierman_update",
        "One Bierman U-D scalar measurement update, in place on (U, d, xi), for y = h . x + noise of unit "
        "variance; returns the innovation and its variance. A sensor without an FPU runs it in float32 (soft "
        "float): no fixed-point file.",
        _ud_cases,
        _ud_compute,
        _ud_tolerance,
    ),
    VectorSpec(
        "refraction_by_addition",
        "float32",
        "onboard.refraction.zenith_geometry, refraction_from_true_zenith, rotate_in_vertical (= "
        "refract_toward_zenith, model atan)",
        "True directions lifted toward the zenith by R(z_t) = A tan z_a + B tan^3 z_a solved for the true zenith "
        "distance (seed 001 sec. 4). A, B [rad] are configuration values (float64 here; the sensor stores them as "
        "float32, as the code casts them).",
        _refraction_cases,
        _refraction_compute,
        _refraction_tolerance,
    ),
    VectorSpec(
        "refraction_by_addition",
        "fixed",
        "onboard.refraction.topocentric_observed_q30 (refraction_from_true_zenith_q36; fixedpoint.isqrt, div_round)",
        "The ground sensor's per-star correction in integers: Q30 directions aberrated by the site velocity beta "
        "(Q48, first order), then lifted toward the Q30 zenith by R (Q36, two Newton steps on the true zenith "
        "distance) with A, B in Q56; beta = 0: the refraction alone.",
        _refraction_fixed_cases,
        _refraction_fixed_compute,
        _exact(("aberrated_q30", "observed_q30")),
        _refraction_fixed_constants,
    ),
    VectorSpec(
        "apparent_place",
        "float32",
        "onboard.earth.true_of_date_matrix, onboard.apparent.apparent_place_vectors",
        "Catalogue vectors (unit, proper motion [rad/yr], parallax [mas], epoch) at TT instant (day since J2000 "
        "int32, fraction of day in 2^-32 uint32) -> geocentric apparent directions in the true equator and "
        "equinox of date; with the GCRS -> TOD matrix.",
        _apparent_cases,
        _apparent_compute,
        _apparent_tolerance,
    ),
    VectorSpec(
        "apparent_place",
        "fixed",
        "onboard.apparent.apparent_place_vectors_q30 (fixedpoint.normalise_q30, div_round)",
        "The per-star apparent place in integers: space motion and light deflection as Q48 changes, aberration to "
        "second order in Q44, normalisation by the integer reciprocal square root, rotation by the Q30 GCRS -> TOD "
        "matrix. The instant's quantities (apparent.fixed_instant: soft float64 once per frame) are inputs.",
        _apparent_fixed_cases,
        _apparent_fixed_compute,
        _exact(("apparent_q30",)),
        _apparent_fixed_constants,
    ),
    VectorSpec(
        "attitude",
        "float32",
        "onboard.attitude.attitude_from_vectors",
        "The C with b = C r minimising Wahba's loss (weights w): any correct solver (SVD, QUEST, ESOQ) followed by "
        "the reference's Gauss-Newton refinement reaches the same float32 floor.",
        _attitude_cases,
        _attitude_compute,
        _attitude_tolerance,
    ),
    VectorSpec(
        "bank_record",
        "bytes",
        "onboard.banks.encode_bank_record, decode_bank_record, encode_stage_record, decode_stage_record",
        "Bank record (magic BNK2, seq, generation, nonce counter, epoch, reserved, the 92-byte table, CRC-32) and "
        "stage record (magic STG2, epoch, counter, CRC-32) bytes, and the verdicts of verification on a valid, a "
        "bit-flipped, a half-programmed and an erased record. Byte formats: the same for the float32 and "
        "fixed-point firmware.",
        _bank_cases,
        _bank_compute,
        _bytes_exact,
    ),
)

#: Functions of the issue that have no fixed-point file yet, and why (docs/port-kit.md lists the coverage).
FIXED_POINT_NOTES: dict[str, str] = {
    "camera_jacobians": "float32 (soft float) on a sensor without an FPU (onboard.fixedpoint module docstring)",
    "ud_update": "float32 (soft float) on a sensor without an FPU (onboard.fixedpoint module docstring)",
    "attitude": "float32 (soft float); no fixed-point attitude in the reference model",
}


# ------------------------------------------------------------------------------------------------ generation
def _document(spec: VectorSpec) -> dict:
    cases = []
    tolerance: dict[str, dict] = {}
    for inp in spec.cases():
        dtype = np.float32 if spec.precision == "float32" else np.float64
        out = spec.compute(inp, dtype)
        tol = spec.tolerance(inp, out)
        cases.append(
            {
                "inputs": {k: encode_array(v) for k, v in inp.items()},
                "outputs": {k: encode_array(v) for k, v in out.items()},
                "tolerance": {k: t.as_json() for k, t in tol.items()},
            }
        )
        for k, t in tol.items():
            tolerance.setdefault(k, {"why": t.why})
    return {
        "format_version": FORMAT_VERSION,
        "function": spec.name,
        "precision": spec.precision,
        "reference": spec.reference,
        "description": spec.description,
        "encoding": "arrays row-major; floats as IEEE-754 bit patterns in hex (value: decimal, informative); "
        "integers as decimal strings; bytes as hex",
        "tolerance_rule": "|port - output| <= tolerance.abs elementwise (abs broadcast against the output); "
        "fixed point and bytes: equal",
        "outputs_tolerance_why": tolerance,
        "constants": {k: encode_array(v) for k, v in (spec.constants() if spec.constants else {}).items()},
        "cases": cases,
    }


def generate_vectors() -> dict[str, dict]:
    """File name -> JSON document of every vector file, plus ``index.json``."""
    docs = {spec.file_name: _document(spec) for spec in SPECS}
    docs["index.json"] = {
        "format_version": FORMAT_VERSION,
        "files": [
            {"file": s.file_name, "function": s.name, "precision": s.precision, "reference": s.reference} for s in SPECS
        ],
        "fixed_point_not_in_integers": FIXED_POINT_NOTES,
        "unit_roundoff_float32": U32,
        "tolerance_model": "float32: gamma_n = n u / (1 - n u) (Higham 2002, Lemma 3.1) times the magnitude the "
        "operations act on, n counted from the code; fixed point and bytes: exact",
    }
    return docs


def write_vectors(directory: str | Path) -> list[Path]:
    """Write every vector file into ``directory`` (created if needed; each file atomically). Returns the paths."""
    from hostlink.errors import UserError
    from hostlink.files.atomic import json_text, write_text

    out = Path(directory)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: not a directory")
    paths = []
    for name, doc in generate_vectors().items():
        path = out / name
        write_text(path, json_text(doc, indent=1) + "\n")
        paths.append(path)
    return paths


# --------------------------------------------------------------------------------------------------- checking
@dataclass(frozen=True)
class Deviation:
    """The largest |got - expected| / tolerance of one output over a file's cases (<= 1 passes; for exact outputs
    0 or inf)."""

    file: str
    output: str
    against: str  # "regenerated" (the Python model in the file's precision) or "float64" (the same code)
    worst_ratio: float
    worst_abs: float


def _ratio(got, expected, tol) -> tuple[float, float]:
    if isinstance(expected, bytes):
        return (0.0, 0.0) if got == expected else (math.inf, math.inf)
    g = np.asarray(got, dtype=np.float64) if np.asarray(got).dtype.kind == "f" else np.asarray(got)
    e = np.asarray(expected, dtype=np.float64) if np.asarray(expected).dtype.kind == "f" else np.asarray(expected)
    if g.shape != e.shape:
        return math.inf, math.inf
    if e.dtype.kind in "iub":
        diff = np.abs(g.astype(object) - e.astype(object)).astype(np.float64) if e.dtype.kind != "b" else (g != e)
        diff = np.asarray(diff, dtype=np.float64)
    else:
        diff = np.abs(g - e)
    worst = float(np.max(diff, initial=0.0))
    t = np.broadcast_to(np.asarray(tol, dtype=np.float64), diff.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(diff == 0, 0.0, diff / t)
    return float(np.max(r, initial=0.0)), worst


def _tolerance_of(obj: dict):
    a = obj["abs"]
    return decode_array(a) if isinstance(a, dict) else a


def check_vectors(directory: str | Path) -> list[Deviation]:
    """Regenerate every output of every vector file in ``directory`` from its stored inputs with the Python model
    and compare within the stored tolerance; for float32 files also compare the float64 run of the same code to
    the stored outputs (the tolerance must cover the reference's own rounding). Returns one :class:`Deviation` per
    (file, output, comparison)."""
    import json

    from hostlink.errors import UserError

    directory = Path(directory)
    out: list[Deviation] = []
    for spec in SPECS:
        path = directory / spec.file_name
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise UserError(f"{path}: cannot read vectors ({exc})") from None
        worst: dict[tuple[str, str], tuple[float, float]] = {}
        for case in doc["cases"]:
            inp = {k: decode_array(v) for k, v in case["inputs"].items()}
            expected = {k: decode_array(v) for k, v in case["outputs"].items()}
            tol = {k: _tolerance_of(v) for k, v in case["tolerance"].items()}
            runs = {"regenerated": spec.compute(inp, np.float32 if spec.precision == "float32" else np.float64)}
            if spec.precision == "float32":
                runs["float64"] = spec.compute(inp, np.float64)
            for against, got in runs.items():
                for name, e in expected.items():
                    r, a = _ratio(got[name], e, tol[name])
                    prev = worst.get((name, against), (0.0, 0.0))
                    worst[(name, against)] = (max(prev[0], r), max(prev[1], a))
        out += [Deviation(spec.file_name, n, ag, r, a) for (n, ag), (r, a) in worst.items()]
    return out


def fixed_point_against_float64(directory: str | Path) -> dict[str, tuple[float, float]]:
    """The fixed-point vectors against the float64 camera model at the parameters they represent (theta_q):
    output -> (worst error, its bound from onboard/fixedpoint.py), in Q30 steps of unit vectors and Q61 steps of
    residuals' float64 value."""
    import json

    doc = json.loads((Path(directory) / "pixel_to_direction.fixed.json").read_text(encoding="utf-8"))
    worst_b, bound_b = 0.0, math.inf
    for case in doc["cases"]:
        inp = {k: decode_array(v) for k, v in case["inputs"].items()}
        got = {k: decode_array(v) for k, v in case["outputs"].items()}
        theta_q = got["theta_q"]
        b64 = camera.pixels_to_unit(inp["x_q10"] / 1024.0, inp["y_q10"] / 1024.0, theta_q)
        worst_b = max(worst_b, float(np.max(np.abs(got["b_q30"] * 2.0**-30 - b64))) * 2.0**30)
        cam = fixedpoint.fixed_camera(inp["theta"], tuple(int(v) for v in inp["image_size_px"]))
        bound_b = min(bound_b, fixedpoint.error_bounds_q30(cam)[1])  # the tightest case's bound, per component
    return {"b_q30": (worst_b, bound_b)}
