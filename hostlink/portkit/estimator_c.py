"""The C numerical core (``onboard/c``: camera, ud, fixedpoint, interstar, recursive, prior, refraction, apparent,
earth, timescale, attitude) bound with ctypes, so the host runs the firmware's estimator beside the Python model
(``hostlink replay --firmware c``) and the tests prove the two equal.

The library is the firmware core's (:func:`hostlink.portkit.firmware_c.load_library`: built once with the machine's
C compiler, the flight-code flags and no fused multiply-add, cached under a hash of the sources; nothing is
downloaded); :func:`load` declares the numerical functions' signatures on it. :class:`CEstimator` holds one estimator
state (``recursive_state_t``, allocated once) and exchanges it with ``onboard.recursive`` through the saved-state
bytes both write (``onboard.recursive.save_state``), so a Python state and a C state can be set equal at any frame.
"""

from __future__ import annotations

import ctypes
from dataclasses import fields
from functools import cache
from pathlib import Path

import numpy as np

from hostlink.portkit import firmware_c
from hostlink.portkit.export_c import core_dir
from onboard import recursive
from onboard.params import ESTIMATE_NAMES, N_PARAMS, CameraParams
from protocol.messages import quantise_px

#: The numerical modules of the C core, one per ``onboard`` module (onboard/c/<module>.c and NAME.h).
NUMERIC_MODULES = (
    "camera",
    "ud",
    "fixedpoint",
    "interstar",
    "recursive",
    "prior",
    "refraction",
    "apparent",
    "attitude",
    "earth",
    "timescale",
)
#: Flight-code flags (issue 27): the firmware core's warnings as errors (C99, conversions and shadowing included) and
#: no contraction of a * b + c into a fused multiply-add (the reference model rounds every product on its own: with
#: it, the float32 results are the model's bits, docs/port-kit.md "The order").
STRICT_FLAGS = (*firmware_c.WARNING_FLAGS, "-ffp-contract=off")
#: The SIL harness's sanitizers: the firmware core's sanitized build's (any finding aborts the run).
SANITIZE_FLAGS = firmware_c.SANITIZE_FLAGS
#: The C core's compile-time sizes (onboard/c/interstar.h INTERSTAR_MAX_STARS, recursive.h RECURSIVE_MAX_DRIFT_WINDOW).
MAX_STARS = 32
MAX_DRIFT_WINDOW = 256
#: Skip reasons of onboard.recursive.FrameResult, by recursive_skip_t.
SKIP_TEXT = (
    "",
    "fewer than 3 identified stars",
    "fewer than 3 consistent stars",
    "most pairs inconsistent with the state",
)


def c_dir() -> Path:
    """onboard/c: the C core's sources, shipped with the package (:func:`hostlink.portkit.export_c.core_dir`)."""
    return core_dir()


def sources(modules: tuple[str, ...] = NUMERIC_MODULES) -> list[Path]:
    """The numerical modules' C files (the SIL harness builds them with its own flags)."""
    return [c_dir() / f"{m}.c" for m in modules]


# ------------------------------------------------------------------------------------------------ ctypes mirror
class Config(ctypes.Structure):
    """recursive_config_t (onboard/c/recursive.h)."""

    _fields_ = [
        ("max_stars", ctypes.c_int32),
        ("centroid_noise_px", ctypes.c_double),
        ("has_prior_sigma", ctypes.c_int32),
        ("prior_sigma", ctypes.c_double * N_PARAMS),
        ("process_noise", ctypes.c_double * N_PARAMS),
        ("pair_gate_sigma", ctypes.c_double),
        ("max_iterations", ctypes.c_int32),
        ("iteration_tol", ctypes.c_double),
        ("reopen_after_frames", ctypes.c_int32),
        ("burn_in_frames", ctypes.c_int32),
        ("burn_in_power", ctypes.c_double),
        ("drift_detect", ctypes.c_int32),
        ("drift_window_frames", ctypes.c_int32),
        ("drift_start_frames", ctypes.c_int32),
        ("drift_threshold", ctypes.c_double),
        ("drift_focal_mm_per_frame", ctypes.c_double),
    ]


class Camera(ctypes.Structure):
    """recursive_camera_t."""

    _fields_ = [
        ("focal_length_mm", ctypes.c_double),
        ("pixel_pitch_um", ctypes.c_double),
        ("principal_point_px", ctypes.c_double * 2),
        ("image_size_px", ctypes.c_int32 * 2),
        ("distortion", ctypes.c_double * 7),
    ]


class FrameResult(ctypes.Structure):
    """recursive_frame_result_t."""

    _fields_ = [
        ("n_stars", ctypes.c_int32),
        ("n_used", ctypes.c_int32),
        ("n_rejected_stars", ctypes.c_int32),
        ("rejected_stars", ctypes.c_int32 * 32),
        ("n_pairs", ctypes.c_int32),
        ("n_pairs_rejected", ctypes.c_int32),
        ("iterations", ctypes.c_int32),
        ("nis", ctypes.c_double),
        ("focal_score", ctypes.c_double),
        ("focal_score_var", ctypes.c_double),
        ("skipped", ctypes.c_int32),
        ("reopened", ctypes.c_int32),
    ]


class TimeTT(ctypes.Structure):
    """timescale_time_t (onboard/c/timescale.h): days since J2000 and the day fraction in 2^-32 day."""

    _fields_ = [("day", ctypes.c_int32), ("frac", ctypes.c_uint32)]


class SeamConfig(ctypes.Structure):
    """estimator_seam_config_t (onboard/c/estimator_seam.h, the firmware core's)."""

    _fields_ = [
        ("estimate_mask", ctypes.c_uint32),
        ("precision", ctypes.c_uint32),
        ("centroid_noise_px", ctypes.c_double),
        ("drift_focal_mm_per_frame", ctypes.c_double),  # 0: the default (RecursiveConfig's 7e-5 mm)
    ]


class FixedInstant(ctypes.Structure):
    """apparent_instant_t (onboard/c/apparent.h)."""

    _fields_ = [
        ("years_q20", ctypes.c_int64),
        ("earth_bary_q30", ctypes.c_int64 * 3),
        ("sun_to_earth_q30", ctypes.c_int64 * 3),
        ("deflection_k_q70", ctypes.c_int64),
        ("beta_q44", ctypes.c_int64 * 3),
        ("tod_q30", ctypes.c_int64 * 9),
    ]


def fixed_instant(inputs: dict) -> FixedInstant:
    """The instant's quantities of an ``apparent_place.fixed.json`` golden vector's inputs (``hostlink vectors``) as
    the C ``apparent_instant_t``: the one conversion the host and target runs of those vectors share."""
    inst = FixedInstant()
    inst.years_q20 = int(inputs["years_q20"])
    inst.deflection_k_q70 = int(inputs["deflection_k_q70"])
    inst.earth_bary_q30[:] = [int(v) for v in inputs["earth_bary_q30"]]
    inst.sun_to_earth_q30[:] = [int(v) for v in inputs["sun_to_earth_q30"]]
    inst.beta_q44[:] = [int(v) for v in inputs["beta_q44"]]
    inst.tod_q30[:] = [int(v) for v in np.ravel(inputs["tod_q30"])]
    return inst


class FixedCamera(ctypes.Structure):
    """fixedpoint_camera_t (onboard/c/fixedpoint.h)."""

    _fields_ = [
        ("s", ctypes.c_int32),
        ("x0_q", ctypes.c_int64),
        ("y0_q", ctypes.c_int64),
        ("coef_m", ctypes.c_int64 * 7),
        ("coef_e", ctypes.c_int32 * 7),
        ("qw", ctypes.c_int32),
        ("f_w", ctypes.c_int64),
        ("width_px", ctypes.c_int32),
        ("height_px", ctypes.c_int32),
        ("theta_q", ctypes.c_double * N_PARAMS),
    ]


_P = ctypes.c_void_p
_SIGNATURES = {
    "camera_ideal_offsets": (None, [_P, _P, ctypes.c_size_t, _P, _P, _P]),
    "camera_offsets_to_unit": (None, [_P, _P, ctypes.c_size_t, ctypes.c_float, _P]),
    "camera_pixels_to_unit": (None, [_P, _P, ctypes.c_size_t, _P, _P]),
    "camera_unit_vector_jacobians": (None, [_P, _P, ctypes.c_size_t, _P, _P, _P, _P]),
    "ud_bierman_update": (ctypes.c_float, [_P, _P, _P, _P, ctypes.c_float, ctypes.c_size_t, _P]),
    "ud_agee_turner_update": (None, [_P, _P, _P, ctypes.c_float, ctypes.c_size_t]),
    "fixedpoint_camera": (ctypes.c_int, [_P, ctypes.c_int32, ctypes.c_int32, _P]),
    "fixedpoint_ideal_offsets_q30": (ctypes.c_int, [ctypes.c_int64, ctypes.c_int64, _P, _P, _P]),
    "fixedpoint_offsets_to_unit_q30": (None, [ctypes.c_int64, ctypes.c_int64, _P, _P]),
    "fixedpoint_normalise_q30": (None, [_P, _P]),
    "fixedpoint_pixels_to_unit_q30": (ctypes.c_int, [ctypes.c_int64, ctypes.c_int64, _P, _P]),
    "fixedpoint_isqrt": (ctypes.c_int64, [ctypes.c_int64]),
    "fixedpoint_div_round": (ctypes.c_int64, [ctypes.c_int64, ctypes.c_int64]),
    "fixedpoint_difference_residuals_q61": (None, [_P, _P, _P, _P, ctypes.c_size_t, _P]),
    "fixedpoint_residuals_to_float": (None, [_P, ctypes.c_size_t, _P]),
    "interstar_independent_pairs": (ctypes.c_size_t, [ctypes.c_size_t, _P, _P]),
    "interstar_order_for_pairs": (None, [_P, _P, ctypes.c_size_t, _P]),
    "interstar_difference_residuals": (None, [_P, _P, _P, _P, ctypes.c_size_t, _P]),
    "interstar_difference_jacobian": (None, [_P, _P, ctypes.c_size_t, _P, _P, ctypes.c_size_t, _P]),
    "interstar_pair_covariance": (None, [_P, _P, _P, _P, ctypes.c_size_t, ctypes.c_double, _P]),
    "recursive_state_size": (ctypes.c_size_t, []),
    "recursive_default_config": (None, [_P]),
    "recursive_create": (ctypes.c_int, [_P, _P, ctypes.c_uint32, _P]),
    "recursive_update": (ctypes.c_int, [_P, _P, _P, _P, _P, ctypes.c_size_t, _P]),
    "recursive_update_fixed": (ctypes.c_int, [_P, _P, _P, _P, _P, ctypes.c_size_t, _P]),
    "recursive_state_vector": (None, [_P, _P]),
    "recursive_sigma": (None, [_P, _P]),
    "recursive_drift_statistic": (ctypes.c_double, [_P]),
    "recursive_update_cost_flops": (ctypes.c_int64, [ctypes.c_int32, ctypes.c_int32, _P]),
    "recursive_save_state": (ctypes.c_size_t, [_P, _P, ctypes.c_size_t]),
    "recursive_restore_state": (ctypes.c_int, [_P, _P, ctypes.c_size_t, _P, _P]),
    "prior_config": (None, [_P, _P, _P, ctypes.c_uint32, _P]),
    "prior_validate_sigma": (ctypes.c_int32, [_P]),
    "prior_refined_mask": (ctypes.c_uint32, [_P]),
    "refraction_zenith_geometry": (None, [_P, ctypes.c_size_t, _P, _P, _P, _P]),
    "refraction_from_true_zenith": (ctypes.c_float, [ctypes.c_float, ctypes.c_float, ctypes.c_double, ctypes.c_double]),
    "refraction_rotate_in_vertical": (None, [_P, ctypes.c_float, _P, ctypes.c_float, ctypes.c_float, _P]),
    "refraction_refract_toward_zenith": (None, [_P, ctypes.c_size_t, _P, ctypes.c_double, ctypes.c_double, _P]),
    "refraction_topocentric_observed_q30": (
        None,
        [_P, ctypes.c_size_t, _P, _P, ctypes.c_int, ctypes.c_int64, ctypes.c_int64, _P],
    ),
    "apparent_place_vectors_q30": (None, [_P, _P, _P, ctypes.c_size_t, _P, _P]),
    "apparent_aberration_change": (None, [_P, _P, _P]),
    "attitude_from_vectors": (ctypes.c_int, [_P, _P, _P, ctypes.c_size_t, _P]),
    "earth_true_of_date_matrix": (None, [TimeTT, _P]),
    "apparent_place_vectors": (None, [_P, _P, _P, ctypes.c_size_t, ctypes.c_double, TimeTT, _P]),
    "estimator_seam_state_bytes": (ctypes.c_size_t, []),
    "estimator_seam_start": (ctypes.c_int, [_P, _P, _P]),
    "estimator_seam_update": (ctypes.c_int, [_P, ctypes.c_uint32, _P, _P, _P, _P]),
    "estimator_seam_estimate": (None, [_P, _P, _P, _P, _P]),
    "estimator_seam_cost_flops": (ctypes.c_uint64, [_P, ctypes.c_uint32]),
}


@cache
def load() -> ctypes.CDLL:
    """The firmware core's library (``hostlink.portkit.firmware_c.load_library``: every onboard/c module, built once
    with the machine's compiler and cached by source hash; no compiler is a one-line UserError) with the numerical
    functions' signatures declared."""
    lib = firmware_c.load_library()
    for name, (restype, argtypes) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


def ptr(a: np.ndarray) -> int:
    """The address of a C-contiguous array (the caller keeps it alive for the call)."""
    assert a.flags.c_contiguous
    return a.ctypes.data


def ref(s: ctypes.Structure) -> int:
    return ctypes.addressof(s)


def c_config(config: recursive.RecursiveConfig) -> Config:
    """onboard.recursive.RecursiveConfig -> recursive_config_t."""
    out = Config()
    for f in fields(config):
        value = getattr(config, f.name)
        if f.name == "prior_sigma":
            out.has_prior_sigma = int(value is not None)
            out.prior_sigma[:] = [float(v) for v in (value if value is not None else (0.0,) * N_PARAMS)]
        elif f.name == "process_noise":
            out.process_noise[:] = [float(v) for v in value]
        else:
            setattr(out, f.name, value if isinstance(getattr(out, f.name), int) else float(value))
    return out


def c_camera(params: CameraParams) -> Camera:
    """onboard.params.CameraParams -> recursive_camera_t."""
    out = Camera()
    out.focal_length_mm = float(params.focal_length_mm)
    out.pixel_pitch_um = float(params.pixel_pitch_um)
    out.principal_point_px[:] = [float(v) for v in params.principal_point_px]
    out.image_size_px[:] = [int(v) for v in params.image_size_px]
    out.distortion[:] = [float(v) for v in params.distortion.as_tuple()]
    return out


def estimated_mask(names: tuple[str, ...]) -> int:
    return sum(1 << ESTIMATE_NAMES.index(n) for n in names)


class CEstimator:
    """One C estimator state (``recursive_state_t``) for ``nominal`` and ``config`` (onboard.recursive's)."""

    def __init__(self, nominal: CameraParams, names: tuple[str, ...], config: recursive.RecursiveConfig) -> None:
        self.lib = load()
        self.nominal = nominal
        self.names = tuple(names)
        self.config = config
        self._camera = c_camera(nominal)
        self._config = c_config(config)
        if config.max_stars > MAX_STARS or config.drift_window_frames > MAX_DRIFT_WINDOW:
            raise ValueError(
                f"max_stars {config.max_stars} / drift window {config.drift_window_frames} frames exceed the C core's "
                f"compile-time sizes (INTERSTAR_MAX_STARS = {MAX_STARS}, RECURSIVE_MAX_DRIFT_WINDOW = "
                f"{MAX_DRIFT_WINDOW})"
            )
        self._state = ctypes.create_string_buffer(int(self.lib.recursive_state_size()))
        self._blob = ctypes.create_string_buffer(1 << 16)
        status = self.lib.recursive_create(
            self._state, ref(self._camera), estimated_mask(self.names), ref(self._config)
        )
        if status != 0:
            raise ValueError(f"the C estimator refused its configuration (status {status})")

    def update(self, x_px, y_px, r_ref, identified, precision: str = "float32") -> recursive.FrameResult:
        """One frame, as onboard.firmware.estimator_update takes it (float64 inputs): "float32" casts them to
        float32 as the Python estimator does; "fixed" quantises them as onboard.fixedpoint.frame_front_end does
        (centroids to Q10 steps, references to Q30). Raises FixedRangeError (fixed) or ValueError (Cholesky)."""
        from onboard.fixedpoint import FixedRangeError, quantise_unit_q30

        n = int(np.shape(x_px)[0])
        x = np.asarray(x_px, dtype=np.float64)
        y = np.asarray(y_px, dtype=np.float64)
        r = np.asarray(r_ref, dtype=np.float64).reshape(-1, 3)
        ident = np.ones(n, dtype=np.uint8) if identified is None else np.asarray(identified, dtype=np.uint8)
        res = FrameResult()
        if precision == "fixed":
            usable = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(r), axis=1) & ident.astype(bool)
            clip = float(1 << 40)
            xq = np.ascontiguousarray(quantise_px(np.clip(np.where(usable, x, 0.0), -clip, clip)), dtype=np.int64)
            yq = np.ascontiguousarray(quantise_px(np.clip(np.where(usable, y, 0.0), -clip, clip)), dtype=np.int64)
            rq = np.ascontiguousarray(quantise_unit_q30(np.where(usable[:, None], r, 0.0)), dtype=np.int64)
            mask = np.ascontiguousarray(usable, dtype=np.uint8)
            status = self.lib.recursive_update_fixed(self._state, ptr(xq), ptr(yq), ptr(rq), ptr(mask), n, ref(res))
        else:
            x32 = np.ascontiguousarray(x, dtype=np.float32)
            y32 = np.ascontiguousarray(y, dtype=np.float32)
            r32 = np.ascontiguousarray(r, dtype=np.float32)
            mask = np.ascontiguousarray(ident)
            status = self.lib.recursive_update(self._state, ptr(x32), ptr(y32), ptr(r32), ptr(mask), n, ref(res))
        if status == 3:
            raise FixedRangeError("the estimate is outside the fixed-point range (fixedpoint_camera)")
        if status != 0:
            raise ValueError(f"the C estimator failed (status {status}: the pair covariance is not positive definite)")
        return frame_result(res)

    def save_state(self) -> bytes:
        """The state as onboard.recursive.save_state's bytes."""
        n = self.lib.recursive_save_state(self._state, self._blob, len(self._blob))
        return bytes(self._blob.raw[:n])

    def restore_state(self, blob: bytes) -> None:
        """Set the state from onboard.recursive.save_state's bytes (float32). Raises ValueError if refused."""
        buf = ctypes.create_string_buffer(bytes(blob), len(blob))
        status = self.lib.recursive_restore_state(self._state, buf, len(blob), ref(self._camera), ref(self._config))
        if status != 0:
            raise ValueError(f"the C estimator refused the saved state (status {status})")

    def state_vector(self) -> np.ndarray:
        out = np.zeros(N_PARAMS, dtype=np.float64)
        self.lib.recursive_state_vector(self._state, ptr(out))
        return out

    def sigma(self) -> np.ndarray:
        """1-sigma per parameter (parameter units, f in mm; NaN where not estimated)."""
        out = np.zeros(N_PARAMS, dtype=np.float64)
        self.lib.recursive_sigma(self._state, ptr(out))
        return out

    def to_python(self) -> recursive.RecursiveState:
        """The same state as an onboard.recursive.RecursiveState (through the saved-state bytes)."""
        return recursive.restore_state(self.save_state(), self.nominal, self.config)


def frame_result(res: FrameResult) -> recursive.FrameResult:
    """recursive_frame_result_t -> onboard.recursive.FrameResult."""
    skipped = SKIP_TEXT[res.skipped] + (" (covariance reopened)" if res.reopened else "")
    return recursive.FrameResult(
        n_stars=res.n_stars,
        n_used=res.n_used,
        rejected_stars=tuple(int(res.rejected_stars[k]) for k in range(res.n_rejected_stars)),
        n_pairs=res.n_pairs,
        n_pairs_rejected=res.n_pairs_rejected,
        iterations=res.iterations,
        nis=float(res.nis),
        focal_score=float(res.focal_score),
        focal_score_var=float(res.focal_score_var),
        skipped=skipped,
    )


#: RecursiveState fields that the saved state carries (onboard.recursive.save_state), copied back by :func:`stepper`.
_SYNCED = (
    "scale",
    "x_hi",
    "x_lo",
    "u",
    "d",
    "q",
    "ring_g",
    "ring_v",
    "frames",
    "updates",
    "drift_on",
    "drift_frame",
    "ring_pos",
    "ring_count",
    "nis_count",
    "inconsistent_run",
    "nis_sum",
    "q_drift",
)


def stepper(state: recursive.RecursiveState):
    """The C estimator in place of ``onboard.firmware.estimator_update`` for a run that starts from ``state`` (a fresh
    Python state, created as the sensor creates it): a function with estimator_update's signature that runs the frame
    in C and then mirrors the C state into ``state`` (through the saved-state bytes), so everything that reads the
    Python state (the replay's trace and estimate) reads the C estimator's. The C state starts as ``state``: its
    saved bytes must equal the Python's, or the C core and the model disagree on the configuration (a ValueError)."""
    names = tuple(ESTIMATE_NAMES[int(k)] for k in state.idx)
    est = CEstimator(state.nominal, names, state.config)
    if est.save_state() != recursive.save_state(state):
        raise ValueError("the C estimator does not start from the Python estimator's state (configuration mismatch)")

    def step(py_state, x_px, y_px, r_ref, identified, precision="float32") -> recursive.FrameResult:
        result = est.update(x_px, y_px, r_ref, identified, precision)
        mirrored = est.to_python()
        for name in _SYNCED:
            value = getattr(mirrored, name)
            if isinstance(value, np.ndarray):
                getattr(py_state, name)[...] = value
            else:
                setattr(py_state, name, value)
        return result

    return step
