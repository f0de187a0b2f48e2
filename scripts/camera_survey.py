"""The unusual-camera survey of docs/camera-model.md ("Supported cameras"), on demand:

    python scripts/camera_survey.py

A grid of cameras: fields of 60, 20, 8 and 2 deg across the longer side; detectors 256 x 256, 1024 x 1024,
2048 x 512, 512 x 2048, 4096 x 3000 and 8192 x 8192 px; pitches 2, 5.5 and 25 um; principal points centred, at
(0.2, 0.8) of the detector, at a corner and on an edge; no distortion, or k1 of either sign, k3, p1 or all terms
together moving the farthest corner by 1 % or 4.9 % of the half-diagonal. For each: the host's check
(``check_plausible``), the sensor's (``banks.check_table``) against the C core's (``params_check_table``, text for
text), ``fixed_camera`` against ``fixedpoint_camera`` (the same verdict), the fixed-point unit vectors at 36 edge
centroids (int64 = exact integers: nothing wraps; C = Python bit for bit; within ``error_bounds_q30`` of float64) and
the float32 model (Python and C) against float64. Prints the counts and the worst errors; exits 1 on any
disagreement. Needs a C compiler (the core is built once and cached)."""

from __future__ import annotations

import itertools
import math
import sys

import numpy as np

from hostlink.portkit import estimator_c, firmware_c
from hostlink.portkit.estimator_c import FixedCamera, ptr, ref
from onboard import banks
from onboard import fixedpoint as fx
from onboard.camera import pixels_to_unit
from onboard.params import CameraParams, Distortion, ParameterError, check_plausible
from protocol.messages import nak_text_bytes

FIELDS_DEG = (60, 20, 8, 2)
SIZES_PX = ((256, 256), (1024, 1024), (2048, 512), (512, 2048), (4096, 3000), (8192, 8192))
PITCHES_UM = (2.0, 5.5, 25.0)
PRINCIPAL_POINTS = ((0.5, 0.5), (0.2, 0.8), (0.0, 0.0), (1.0, 0.3))  # fractions of (W - 1, H - 1)
DISTORTIONS = ("none", "k1-", "k1+", "k3-", "p1", "all")
FRACTIONS = (0.01, 0.049)  # displacement at the farthest corner / half-diagonal


def distortion(kind: str, size: tuple[int, int], pp: tuple[float, float], fraction: float) -> Distortion:
    """Coefficients moving the farthest corner by ``fraction`` of the half-diagonal."""
    w, h = size
    du = max(abs(-0.5 - pp[0]), abs(w - 0.5 - pp[0]))
    dv = max(abs(-0.5 - pp[1]), abs(h - 0.5 - pp[1]))
    r = math.hypot(du, dv)
    d = fraction * 0.5 * math.hypot(w, h)
    return {
        "none": Distortion(),
        "k1-": Distortion(k1=-d / r**3),
        "k1+": Distortion(k1=d / r**3),
        "k3-": Distortion(k3=-d / r**7),
        "p1": Distortion(p1=d / r**2 / 3),
        "all": Distortion(
            k1=-0.5 * d / r**3, k2=0.2 * d / r**5, p1=0.1 * d / r**2, p2=-0.1 * d / r**2, s1=0.05 * d / r**2
        ),
    }[kind]


def survey() -> dict:
    lib = estimator_c.load()
    out = {"cameras": 0, "refused_host": 0, "refused_fixed": 0, "disagreements": 0, "fixed_err_px": 0.0}
    out["fixed_err_over_bound"] = 0.0
    out["float32_err_px"] = 0.0
    grid = itertools.product(FIELDS_DEG, SIZES_PX, PITCHES_UM, PRINCIPAL_POINTS, DISTORTIONS, FRACTIONS)
    for fov, size, pitch, frac_pp, kind, fraction in grid:
        if kind == "none" and fraction != FRACTIONS[0]:
            continue
        w, h = size
        pp = (frac_pp[0] * (w - 1), frac_pp[1] * (h - 1))
        focal_px = 0.5 * max(w, h) / math.tan(math.radians(fov) / 2)
        params = CameraParams(focal_px * pitch / 1000, pitch, pp, size, distortion(kind, size, pp, fraction))
        out["cameras"] += 1
        try:
            check_plausible(params, None)
        except ParameterError:
            out["refused_host"] += 1
            continue
        table = banks.params_to_table(params)
        refusal = banks.check_table(table, None)
        want = None if refusal is None else nak_text_bytes(refusal.text).decode()
        if firmware_c.check_table_c(table, None) != want:
            out["disagreements"] += 1
            print("sensor checks differ:", params, file=sys.stderr)
        if refusal is not None:
            continue
        theta = np.ascontiguousarray(params.model_vector(np.float32))
        x32, y32 = (
            a.ravel().astype(np.float32) for a in np.meshgrid([-0.5, 0.0, w / 2, w - 0.5], [-0.5, 0, h / 2, h - 0.5])
        )
        b_c = np.zeros((x32.size, 3), np.float32)
        lib.camera_pixels_to_unit(ptr(x32), ptr(y32), x32.size, ptr(theta), ptr(b_c))
        b64 = pixels_to_unit(x32.astype(np.float64), y32.astype(np.float64), theta.astype(np.float64))
        err32 = max(np.abs(b_c - b64).max(), np.abs(pixels_to_unit(x32, y32, theta) - b64).max())
        out["float32_err_px"] = max(out["float32_err_px"], float(err32) * params.focal_length_px)
        try:
            cam = fx.fixed_camera(theta, size)
        except fx.FixedRangeError:
            cam = None
            out["refused_fixed"] += 1
        cam_c = FixedCamera()
        if (lib.fixedpoint_camera(ptr(theta), w, h, ref(cam_c)) == 0) != (cam is not None):
            out["disagreements"] += 1
            print("fixed-point verdicts differ:", params, file=sys.stderr)
        if cam is None:
            continue
        ex, ey = [-0.5, 0.0, 1.0, w / 2, w - 1.5, w - 0.5], [-0.5, 0.0, 1.0, h / 2, h - 1.5, h - 0.5]
        gx, gy = np.meshgrid(ex, ey)
        xs, ys = (np.rint(a.ravel() * 1024).astype(np.int64) for a in (gx, gy))
        b = fx.pixels_to_unit_q30(xs, ys, cam)
        exact = fx.pixels_to_unit_q30(xs.astype(object), ys.astype(object), cam)
        err = float(np.abs(b * 2.0**-30 - pixels_to_unit(xs * 2.0**-10, ys * 2.0**-10, cam.theta_q)).max())
        out["fixed_err_px"] = max(out["fixed_err_px"], err * params.focal_length_px)
        out["fixed_err_over_bound"] = max(out["fixed_err_over_bound"], err * 2**30 / fx.error_bounds_q30(cam)[1])
        c_bytes = []
        for k in range(xs.size):
            bb = np.zeros(3, np.int64)
            lib.fixedpoint_pixels_to_unit_q30(int(xs[k]), int(ys[k]), ref(cam_c), ptr(bb))
            c_bytes.append(bb)
        if not (np.array_equal(exact.astype(np.int64), b) and np.array_equal(np.array(c_bytes), b)):
            out["disagreements"] += 1
            print("fixed-point bytes differ or wrapped:", params, file=sys.stderr)
    return out


def main() -> int:
    result = survey()
    for key, value in result.items():
        print(f"{key}: {value:.3g}" if isinstance(value, float) else f"{key}: {value}")
    return 1 if result["disagreements"] else 0


if __name__ == "__main__":
    sys.exit(main())
