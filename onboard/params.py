"""Camera parameter set: the data class, its parameter vector, and its validation.

The meaning of every field is fixed by ``shared/spec/CAMERA_MODEL.md``. This module holds no I/O: the host reads
and writes JSON files (``hostlink.files.params``); the sensor receives the same fields over the link. Both validate with
:func:`validate_params`, so a set means the same thing, and is accepted or refused for the same reason, on every side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

#: Names of the estimable parameters, in the order of every parameter vector in the project (``--estimate`` names).
ESTIMATE_NAMES: tuple[str, ...] = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "s1", "s2")
#: Distortion keys of the parameter file, in vector order (vector index = 3 + position here).
DISTORTION_KEYS: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "s1", "s2")
N_PARAMS = len(ESTIMATE_NAMES)

#: Grid used by the monotonicity check: points per detector side (corners and edges included).
_MONOTONIC_GRID = 17


class ParameterError(ValueError):
    """A parameter set that must not be used. ``field`` names the offending key as it appears in the file."""

    def __init__(self, field_name: str, reason: str) -> None:
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


@dataclass(frozen=True)
class Distortion:
    """Weng distortion coefficients (CAMERA_MODEL.md): radial k1..k3 [px^-2, px^-4, px^-6], decentering p1 p2
    and thin prism s1 s2 [px^-1]."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    s1: float = 0.0
    s2: float = 0.0

    def as_tuple(self) -> tuple[float, ...]:
        return tuple(getattr(self, k) for k in DISTORTION_KEYS)


@dataclass(frozen=True)
class CameraParams:
    """One camera parameter set, exactly the fields of the parameter file."""

    focal_length_mm: float
    pixel_pitch_um: float
    principal_point_px: tuple[float, float]
    image_size_px: tuple[int, int]
    distortion: Distortion = field(default_factory=Distortion)

    @property
    def focal_length_px(self) -> float:
        """F = 1000 f / p (CAMERA_MODEL.md)."""
        return 1000.0 * self.focal_length_mm / self.pixel_pitch_um

    def vector(self, dtype: type | np.dtype = np.float64) -> np.ndarray:
        """Parameter vector in ESTIMATE_NAMES order, with the focal length in millimetres."""
        return np.array([self.focal_length_mm, *self.principal_point_px, *self.distortion.as_tuple()], dtype=dtype)

    def model_vector(self, dtype: type | np.dtype = np.float64) -> np.ndarray:
        """Vector the camera-model functions take: as :meth:`vector` but with F in pixels in slot 0."""
        theta = self.vector(np.float64)
        theta[0] = self.focal_length_px
        return theta.astype(dtype)

    def with_vector(self, theta: np.ndarray) -> CameraParams:
        """A copy with the estimable parameters replaced by ``theta`` (ESTIMATE_NAMES order, f in mm)."""
        t = [float(v) for v in np.asarray(theta, dtype=np.float64)]
        return replace(
            self,
            focal_length_mm=t[0],
            principal_point_px=(t[1], t[2]),
            distortion=Distortion(*t[3:]),
        )

    def with_model_vector(self, theta: np.ndarray) -> CameraParams:
        """A copy with the parameters of a model vector (slot 0 = F in pixels, as :meth:`model_vector`)."""
        vec = np.array(theta, dtype=np.float64)
        vec[0] = vec[0] * self.pixel_pitch_um / 1000.0  # f = F p / 1000
        return self.with_vector(vec)

    def with_focal_length_mm(self, focal_length_mm: float) -> CameraParams:
        return replace(self, focal_length_mm=float(focal_length_mm))


def params_from_dict(data: dict, validate: bool = True) -> CameraParams:
    """Build (and validate) a parameter set from the JSON object of a parameter file.

    Unknown top-level keys are ignored (a calibration result carries extras). Missing distortion keys are zero.
    Raises :class:`ParameterError` naming the field on any missing, mistyped or invalid value (``validate=False``
    checks only the form, not the ranges of :func:`validate_params`: a test hook that lets a sensor refuse them).
    """
    if not isinstance(data, dict):
        raise ParameterError("(file)", "expected a JSON object with the camera parameter keys")

    def number(key: str, value: object) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(key, f"expected a number, got {value!r}")
        return float(value)

    def pair(key: str) -> tuple[float, float]:
        value = data.get(key)
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ParameterError(key, f"expected a list of two numbers, got {value!r}")
        return number(f"{key}[0]", value[0]), number(f"{key}[1]", value[1])

    for key in ("focal_length_mm", "pixel_pitch_um", "principal_point_px", "image_size_px"):
        if key not in data:
            raise ParameterError(key, "missing")
    dist_obj = data.get("distortion", {}) or {}
    if not isinstance(dist_obj, dict):
        raise ParameterError("distortion", f"expected an object with keys {' '.join(DISTORTION_KEYS)}")
    unknown = sorted(set(dist_obj) - set(DISTORTION_KEYS))
    if unknown:
        raise ParameterError(f"distortion.{unknown[0]}", f"unknown key (allowed: {' '.join(DISTORTION_KEYS)})")
    width, height = pair("image_size_px")
    for key, value in (("image_size_px[0]", width), ("image_size_px[1]", height)):
        if not (math.isfinite(value) and value == int(value)):
            raise ParameterError(key, f"expected a whole number of pixels, got {value!r}")
    params = CameraParams(
        focal_length_mm=number("focal_length_mm", data["focal_length_mm"]),
        pixel_pitch_um=number("pixel_pitch_um", data["pixel_pitch_um"]),
        principal_point_px=pair("principal_point_px"),
        image_size_px=(int(width), int(height)),
        distortion=Distortion(**{k: number(f"distortion.{k}", dist_obj.get(k, 0.0)) for k in DISTORTION_KEYS}),
    )
    if validate:
        validate_params(params)
    return params


def params_to_dict(params: CameraParams) -> dict:
    """The JSON object of a parameter file (plain Python floats; extras are added by the caller)."""
    return {
        "focal_length_mm": float(params.focal_length_mm),
        "pixel_pitch_um": float(params.pixel_pitch_um),
        "principal_point_px": [float(params.principal_point_px[0]), float(params.principal_point_px[1])],
        "image_size_px": [int(params.image_size_px[0]), int(params.image_size_px[1])],
        "distortion": {k: float(getattr(params.distortion, k)) for k in DISTORTION_KEYS},
    }


def validate_params(params: CameraParams) -> None:
    """Refuse a parameter set that no sensor may use (raises :class:`ParameterError` naming the field).

    Checks, in order: every value finite; f > 0 and p > 0; image size positive; the principal point on the detector
    (``[-0.5, w-0.5] x [-0.5, h-0.5]``, CAMERA_MODEL.md); and the distortion keeps the measured-to-ideal mapping
    monotonic over the detector: the Jacobian determinant of (x, y) -> (u', v') is positive on a 17 x 17 grid
    spanning the detector, corners included. Work is bounded (289 points), so the sensor runs the same check.
    """
    scalars = [("focal_length_mm", params.focal_length_mm), ("pixel_pitch_um", params.pixel_pitch_um)]
    scalars += [(f"principal_point_px[{i}]", params.principal_point_px[i]) for i in range(2)]
    scalars += [(f"image_size_px[{i}]", params.image_size_px[i]) for i in range(2)]
    scalars += [(f"distortion.{k}", getattr(params.distortion, k)) for k in DISTORTION_KEYS]
    for name, value in scalars:
        if not math.isfinite(float(value)):
            raise ParameterError(name, f"must be finite, got {value!r}")
    if params.focal_length_mm <= 0:
        raise ParameterError("focal_length_mm", f"must be > 0, got {params.focal_length_mm!r}")
    if params.pixel_pitch_um <= 0:
        raise ParameterError("pixel_pitch_um", f"must be > 0, got {params.pixel_pitch_um!r}")
    width, height = params.image_size_px
    for i, n in enumerate((width, height)):
        if n < 1:
            raise ParameterError(f"image_size_px[{i}]", f"must be >= 1, got {n!r}")
    for i, (c, n) in enumerate(zip(params.principal_point_px, (width, height), strict=True)):
        if not (-0.5 <= c <= n - 0.5):
            raise ParameterError(f"principal_point_px[{i}]", f"{c!r} is off the detector [-0.5, {n - 0.5}]")
    det_min, where = min_mapping_determinant(params)
    if not det_min > 0:
        raise ParameterError(
            "distortion",
            f"mapping is not monotonic over the detector (Jacobian determinant {det_min:.3g} "
            f"at pixel ({where[0]:.0f}, {where[1]:.0f}))",
        )


def min_mapping_determinant(params: CameraParams) -> tuple[float, tuple[float, float]]:
    """Smallest Jacobian determinant of (x, y) -> (u', v') over the detector grid, and where it occurs."""
    from onboard.camera import ideal_offset_jacobians  # local: camera imports this module

    width, height = params.image_size_px
    xs = np.linspace(-0.5, width - 0.5, _MONOTONIC_GRID)
    ys = np.linspace(-0.5, height - 0.5, _MONOTONIC_GRID)
    gx, gy = np.meshgrid(xs, ys)
    _, _, j_centroid = ideal_offset_jacobians(gx.ravel(), gy.ravel(), params.model_vector())
    det = j_centroid[:, 0, 0] * j_centroid[:, 1, 1] - j_centroid[:, 0, 1] * j_centroid[:, 1, 0]
    k = int(np.argmin(det))
    return float(det[k]), (float(gx.ravel()[k]), float(gy.ravel()[k]))


def distortion_from_seed004(k1_seed: float, k2_seed: float) -> Distortion:
    """Seed 004 eq. 6 writes the ideal point as x_hat = x_d + (x_d - x0)(k1 r^2 + k2 r^4), r the radius in pixels.
    In this project's convention (ideal = measured - correction) that is k1 = -k1_seed, k2 = -k2_seed."""
    return Distortion(k1=-float(k1_seed), k2=-float(k2_seed))


def distortion_to_seed004(distortion: Distortion) -> tuple[float, float]:
    """Inverse of :func:`distortion_from_seed004` (only the radial k1, k2 exist in seed 004)."""
    return -distortion.k1, -distortion.k2


def field_names() -> tuple[str, ...]:
    return tuple(f.name for f in fields(CameraParams))
