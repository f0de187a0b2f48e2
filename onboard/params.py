"""Camera parameter set: the data class, its parameter vector, and its validation.

The meaning of every field is fixed by docs/camera-model.md. This module holds no I/O: the host reads
and writes JSON files (``hostlink.files.params``); the sensor receives the same fields over the link. Both validate with
:func:`validate_params`, so a set means the same thing, and is accepted or refused for the same reason, on every side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from protocol.param_table import DISTORTION_NAMES, ESTIMATE_NAMES

# ESTIMATE_NAMES (the estimable parameters, in the order of every parameter vector in the project: ``--estimate``
# names) and DISTORTION_NAMES (the parameter file's distortion keys, vector index = 3 + position) are defined once,
# in the parameter table's layout; they are re-exported here for the camera-model side.
N_PARAMS = len(ESTIMATE_NAMES)

#: Largest detector side [px]: image sizes travel as float32 in the parameter table, exact up to 2**24.
MAX_IMAGE_SIDE_PX = 1 << 24
#: Largest distance [px] from the principal point to the farthest detector corner: the radial terms' Jacobian column
#: of k3, u r^6 <= r^7, stays finite in a float32 sensor (2^126 < 3.4e38 = float32's largest) only up to ~3.2e5 px;
#: 2^18 px leaves a factor 4. Beyond it the float32 estimator overflowed (the Python model faulted on every frame, the C
#: core reported NaN estimates). A 370 000 px square detector, or a 524 288 px strip with the principal point centred.
MAX_CORNER_RADIUS_PX = 1 << 18
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
    """Weng distortion coefficients (docs/camera-model.md): radial k1..k3 [px^-2, px^-4, px^-6], decentering p1 p2
    and thin prism s1 s2 [px^-1]."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    s1: float = 0.0
    s2: float = 0.0

    def as_tuple(self) -> tuple[float, ...]:
        return tuple(getattr(self, k) for k in DISTORTION_NAMES)


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
        """F = 1000 f / p (docs/camera-model.md)."""
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
        try:
            return float(value)
        except OverflowError:  # a JSON integer beyond the float range
            raise ParameterError(key, f"an integer of {value.bit_length()} bits, beyond the float range") from None

    def pair(key: str) -> tuple[float, float]:
        value = data.get(key)
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise ParameterError(key, f"expected a list of two numbers, got {value!r}")
        return number(f"{key}[0]", value[0]), number(f"{key}[1]", value[1])

    for key in ("focal_length_mm", "pixel_pitch_um", "principal_point_px", "image_size_px"):
        if key not in data:
            raise ParameterError(key, "missing")
    dist_obj = data.get("distortion")
    if dist_obj is None:  # absent or null: no distortion (a 0, false, "" or [] is a wrong type, not "none")
        dist_obj = {}
    if not isinstance(dist_obj, dict):
        raise ParameterError("distortion", f"expected an object with keys {' '.join(DISTORTION_NAMES)}")
    unknown = sorted(set(dist_obj) - set(DISTORTION_NAMES))
    if unknown:
        raise ParameterError(f"distortion.{unknown[0]}", f"unknown key (allowed: {' '.join(DISTORTION_NAMES)})")
    width, height = pair("image_size_px")
    for key, value in (("image_size_px[0]", width), ("image_size_px[1]", height)):
        if not (math.isfinite(value) and value == int(value)):
            raise ParameterError(key, f"expected a whole number of pixels, got {value!r}")
    params = CameraParams(
        focal_length_mm=number("focal_length_mm", data["focal_length_mm"]),
        pixel_pitch_um=number("pixel_pitch_um", data["pixel_pitch_um"]),
        principal_point_px=pair("principal_point_px"),
        image_size_px=(int(width), int(height)),
        distortion=Distortion(**{k: number(f"distortion.{k}", dist_obj.get(k, 0.0)) for k in DISTORTION_NAMES}),
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
        "distortion": {k: float(getattr(params.distortion, k)) for k in DISTORTION_NAMES},
    }


def validate_params(params: CameraParams, dtype: type = np.float64) -> None:
    """Refuse a parameter set that no sensor may use (raises :class:`ParameterError` naming the field).

    Checks, in order: every value finite; f > 0 and p > 0 (and F = 1000 f / p finite); image size in 1..2**24; the
    principal point on the detector (``[-0.5, w-0.5] x [-0.5, h-0.5]``, docs/camera-model.md); the farthest corner
    within :data:`MAX_CORNER_RADIUS_PX` of it; and the distortion keeps
    the measured-to-ideal mapping one-to-one over the detector: the radial map r -> r (1 - k1 r^2 - k2 r^4 - k3 r^6)
    strictly increasing for every radius from 0 to the farthest corner (exact: :func:`min_radial_slope`), and the
    Jacobian determinant of (x, y) -> (u', v') positive on a 17 x 17 grid spanning the detector, corners included.
    Work is bounded (289 points and one quadratic), so the sensor runs the same check, in its precision (``dtype``:
    float32 on the sensor, float64 on the host). Physical plausibility (magnitudes against the design) is
    :func:`check_plausible`.
    """
    scalars = [("focal_length_mm", params.focal_length_mm), ("pixel_pitch_um", params.pixel_pitch_um)]
    scalars += [(f"principal_point_px[{i}]", params.principal_point_px[i]) for i in range(2)]
    scalars += [(f"image_size_px[{i}]", params.image_size_px[i]) for i in range(2)]
    scalars += [(f"distortion.{k}", getattr(params.distortion, k)) for k in DISTORTION_NAMES]
    for name, value in scalars:
        if not math.isfinite(float(value)):
            raise ParameterError(name, f"must be finite, got {value!r}")
    if params.focal_length_mm <= 0:
        raise ParameterError("focal_length_mm", f"must be > 0, got {params.focal_length_mm!r}")
    if params.pixel_pitch_um <= 0:
        raise ParameterError("pixel_pitch_um", f"must be > 0, got {params.pixel_pitch_um!r}")
    width, height = params.image_size_px
    for i, n in enumerate((width, height)):
        if not 1 <= n <= MAX_IMAGE_SIDE_PX:
            raise ParameterError(f"image_size_px[{i}]", f"must be in 1..{MAX_IMAGE_SIDE_PX}, got {n:.6g}")
    if not math.isfinite(params.focal_length_px):
        raise ParameterError(
            "focal_length_mm", f"the focal length in pixels 1000 f / p = {params.focal_length_px!r} is not finite"
        )
    for i, (c, n) in enumerate(zip(params.principal_point_px, (width, height), strict=True)):
        if not (-0.5 <= c <= n - 0.5):
            raise ParameterError(f"principal_point_px[{i}]", f"{c!r} is off the detector [-0.5, {n - 0.5}]")
    s_max = farthest_corner_radius2_px2(params)
    if not s_max <= float(MAX_CORNER_RADIUS_PX) ** 2:
        raise ParameterError(
            "image_size_px",
            f"the farthest corner is {math.sqrt(s_max):.0f} px from the principal point, beyond "
            f"{MAX_CORNER_RADIUS_PX} px (a float32 sensor's distortion Jacobian r^7 would overflow)",
        )
    p_min, r_at = min_radial_slope(params.distortion, s_max, dtype)
    if not p_min > 0:
        raise ParameterError(
            "distortion",
            f"radial mapping is not one-to-one: d r'/d r = {p_min:.3g} at radius {r_at:.3g} px "
            f"(the farthest corner is at {math.sqrt(s_max):.0f} px)",
        )
    det_min, where = min_mapping_determinant(params, dtype)
    if not det_min > 0:
        raise ParameterError(
            "distortion",
            f"mapping is not monotonic over the detector (Jacobian determinant {det_min:.3g} "
            f"at pixel ({where[0]:.0f}, {where[1]:.0f}))",
        )


def farthest_corner_radius2_px2(params: CameraParams) -> float:
    """Squared distance [px^2] from the principal point to the farthest detector corner (docs/camera-model.md)."""
    width, height = params.image_size_px
    x0, y0 = params.principal_point_px
    du = max(abs(-0.5 - x0), abs(width - 0.5 - x0))
    dv = max(abs(-0.5 - y0), abs(height - 0.5 - y0))
    return float(du * du + dv * dv)


def min_radial_slope(distortion: Distortion, s_max_px2: float, dtype: type = np.float64) -> tuple[float, float]:
    """Smallest slope d r'/d r of the radial map r' = r (1 - k1 r^2 - k2 r^4 - k3 r^6) over r^2 = s in [0, s_max]
    and the radius [px] where it occurs. The slope is P(s) = 1 - 3 k1 s - 5 k2 s^2 - 7 k3 s^3 (docs/camera-model.md,
    radial terms); a cubic's minimum on an interval is at an end or at a real root of P'(s) = -3 k1 - 10 k2 s -
    21 k3 s^2, found in closed form, so the test is exact at the cost of one quadratic."""
    one, two, three, four, five, seven, ten, c21 = (dtype(v) for v in (1, 2, 3, 4, 5, 7, 10, 21))
    k1, k2, k3 = dtype(distortion.k1), dtype(distortion.k2), dtype(distortion.k3)
    s_max = dtype(s_max_px2)
    candidates = [dtype(0), s_max]
    with np.errstate(all="ignore"):  # a huge coefficient overflows to inf / NaN, which the caller refuses
        a, b, c = -c21 * k3, -ten * k2, -three * k1  # P'(s) = a s^2 + b s + c
        if a != 0:
            disc = b * b - four * a * c
            if disc >= 0:
                root = np.sqrt(disc)
                candidates += [(-b - root) / (two * a), (-b + root) / (two * a)]
        elif b != 0:
            candidates.append(-c / b)
        s = np.array([v for v in candidates if np.isfinite(v) and dtype(0) <= v <= s_max], dtype=dtype)
        slope = one - s * (three * k1 + s * (five * k2 + s * (seven * k3)))
    k = int(np.argmin(slope))
    return float(slope[k]), float(np.sqrt(s[k]))


def min_mapping_determinant(params: CameraParams, dtype: type = np.float64) -> tuple[float, tuple[float, float]]:
    """Smallest Jacobian determinant of (x, y) -> (u', v') over the detector grid, and where it occurs (in
    ``dtype``)."""
    from onboard.camera import ideal_offset_jacobians  # local: camera imports this module

    width, height = params.image_size_px
    xs = np.linspace(-0.5, width - 0.5, _MONOTONIC_GRID, dtype=dtype)
    ys = np.linspace(-0.5, height - 0.5, _MONOTONIC_GRID, dtype=dtype)
    gx, gy = np.meshgrid(xs, ys)
    with np.errstate(all="ignore"):  # an absurd set overflows: NaN counts as not monotonic
        _, _, j_centroid = ideal_offset_jacobians(gx.ravel(), gy.ravel(), params.model_vector(dtype))
        det = j_centroid[:, 0, 0] * j_centroid[:, 1, 1] - j_centroid[:, 0, 1] * j_centroid[:, 1, 0]
    det = np.where(np.isnan(det), -np.inf, det)
    k = int(np.argmin(det))
    return float(det[k]), (float(gx.ravel()[k]), float(gy.ravel()[k]))


def distortion_from_seed004(k1_seed: float, k2_seed: float) -> Distortion:
    """Seed 004 eq. 6 writes the ideal point as x_hat = x_d + (x_d - x0)(k1 r^2 + k2 r^4), r the radius in pixels.
    In this project's convention (ideal = measured - correction) that is k1 = -k1_seed, k2 = -k2_seed."""
    return Distortion(k1=-float(k1_seed), k2=-float(k2_seed))


def distortion_to_seed004(distortion: Distortion) -> tuple[float, float]:
    """Inverse of :func:`distortion_from_seed004` (only the radial k1, k2 exist in seed 004)."""
    return -distortion.k1, -distortion.k2


# ------------------------------------------------------------------------------------------ physical plausibility
#: Largest distortion displacement |(dx, dy)| allowed anywhere on the detector, as a fraction of the detector's
#: half-diagonal. Star-tracker optics stay well under 1 % (seed 004's camera: 0.72 px at its farthest corner, 1e-3
#: of the 724 px half-diagonal); 5 % (36 px on a 1024 x 1024 detector) leaves room for a wide-field lens and refuses
#: a set in another convention (OpenCV's normalised k1 = -0.12 taken as px^-2 moves a corner by 5e7 px).
MAX_DISTORTION_FRACTION = 0.05
#: Largest relative difference between a set's focal length and the sensor's design value: calibrations move f by
#: a fraction of a percent (seed 004: 0.32 %); a unit slip (mm for um, a pitch binning) moves it by 2x or 1000x.
FOCAL_TOLERANCE = 0.05


@dataclass(frozen=True)
class PlausibilityLimits:
    """What a sensor declares about itself: its design focal length [mm] and the allowed departures from it."""

    design_focal_length_mm: float
    focal_tolerance: float = FOCAL_TOLERANCE
    max_distortion_fraction: float = MAX_DISTORTION_FRACTION
    #: what the focal length is compared with, as a refusal names it
    design_name: str = "design value"
    #: the sensor runs the fixed-point front end (``onboard.fixedpoint``): a set must lie in its formats' range
    fixed_point: bool = False


def max_distortion_displacement_px(params: CameraParams, dtype: type = np.float64) -> tuple[float, tuple[float, float]]:
    """Largest |(dx, dy)| [px] of the Weng correction (docs/camera-model.md) on the 17 x 17 detector grid (corners
    included), and the pixel where it occurs, computed in ``dtype``."""
    from onboard.camera import distortion_px  # local: camera imports this module

    width, height = params.image_size_px
    gx, gy = np.meshgrid(
        np.linspace(-0.5, width - 0.5, _MONOTONIC_GRID, dtype=dtype),
        np.linspace(-0.5, height - 0.5, _MONOTONIC_GRID, dtype=dtype),
    )
    theta = params.model_vector(dtype)
    with np.errstate(all="ignore"):  # an absurd set overflows to inf, which the bound refuses
        dx, dy = distortion_px(gx.ravel() - theta[1], gy.ravel() - theta[2], theta)
        size = np.hypot(dx, dy)
    size = np.where(np.isnan(size), np.inf, size)
    k = int(np.argmax(size))
    return float(size[k]), (float(gx.ravel()[k]), float(gy.ravel()[k]))


def check_plausible(params: CameraParams, limits: PlausibilityLimits | None, dtype: type = np.float64) -> None:
    """The one plausibility check, run by the host before sending a set and by the sensor before committing it.
    Raises :class:`ParameterError` whose text names the rule. In order:

    1. :func:`validate_params` (finite values, principal point on the detector, a one-to-one mapping);
    2. distortion bound: max |(dx, dy)| over the detector <= ``max_distortion_fraction`` x half-diagonal;
    3. focal range: |f - f_design| <= ``focal_tolerance`` x f_design (skipped when ``limits`` is None, e.g. on a host
       that does not know the sensor's design; rule 2 then uses the default fraction);
    4. on a fixed-point sensor (``limits.fixed_point``), the range of its formats
       (:func:`onboard.fixedpoint.fixed_camera` at the float32 model vector the estimator starts from), so the sensor
       never commits a set its estimator could not run.
    """
    validate_params(params, dtype)
    fraction = MAX_DISTORTION_FRACTION if limits is None else limits.max_distortion_fraction
    width, height = params.image_size_px
    bound_px = fraction * 0.5 * math.hypot(width, height)
    size_px, where = max_distortion_displacement_px(params, dtype)
    if not size_px <= bound_px:
        raise ParameterError(
            "distortion",
            f"implausible: displacement {size_px:.3g} px at pixel ({where[0]:.0f}, {where[1]:.0f}) exceeds the "
            f"bound {bound_px:.3g} px ({fraction:.0%} of the half-diagonal)",
        )
    if limits is None:
        return
    design = limits.design_focal_length_mm
    if not abs(params.focal_length_mm - design) <= limits.focal_tolerance * design:
        raise ParameterError(
            "focal_length_mm",
            f"implausible: {params.focal_length_mm:.6g} mm is more than {limits.focal_tolerance:.0%} from the "
            f"{limits.design_name} {design:.6g} mm",
        )
    if limits.fixed_point:
        from onboard.fixedpoint import FixedRangeError, fixed_camera  # local: fixedpoint imports this module

        try:
            fixed_camera(params.model_vector(np.float32), params.image_size_px)
        except FixedRangeError as exc:
            raise ParameterError("fixed point", f"outside the sensor's range: {exc}") from None
