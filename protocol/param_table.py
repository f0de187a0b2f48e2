"""The parameter table: how a camera parameter set travels (every transport) and is stored (sensor banks).

A table is 23 IEEE-754 float32 values, little-endian, in :data:`PARAM_FIELDS` order (92 bytes): the 13 camera
fields (:data:`CAMERA_FIELDS`), then the 1-sigma prior of each estimable parameter (:data:`SIGMA_FIELDS`, in
:data:`ESTIMATE_NAMES` order, parameter units: f in mm). The camera fields are the keys of a camera
parameter file (docs/camera-model.md), flattened; ``image_size_px`` travels as float32 too (exact for any
size below 2**24). A sigma is a finite value >= 0, or NaN: NaN or 0 means "unknown", and the sensor's estimator then
starts that parameter from its cold-start prior (``onboard.prior``). The CRC of a set is :func:`protocol.crc.crc32`
over the 92 table bytes. This module is the single definition of the layout: sizes, the CAN DBC field choices, the
Modbus mailbox checks and the bank records all derive from it.

"Equal to float32" (docs/commands.md, ``hostlink upload``) means: every file value rounded to float32 (round to
nearest even, as numpy does) equals the value the sensor reports, bit for bit.

Pure: bytes in, values out. The parameter names (:data:`DISTORTION_NAMES`, :data:`ESTIMATE_NAMES`) are defined in
:mod:`protocol.names`, at the bottom layer, so that the wire, the sensor and the host spell them once;
:func:`camera_fields_from_file` and :func:`camera_file_from_fields` flatten a parameter-file object into the table's
camera fields and back. The mapping to ``onboard.params.CameraParams`` lives in ``onboard.banks`` (protocol imports
nothing from onboard).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from protocol.crc import crc32
from protocol.names import DISTORTION_NAMES, ESTIMATE_NAMES

#: Units of the distortion coefficients (docs/camera-model.md: radial terms in powers of r^2, the others per px).
DISTORTION_UNITS = {
    "k1": "px^-2",
    "k2": "px^-4",
    "k3": "px^-6",
    "p1": "px^-1",
    "p2": "px^-1",
    "s1": "px^-1",
    "s2": "px^-1",
}
#: Camera fields of the table. Names are those of the parameter file (``principal_point_px``/``image_size_px`` split).
CAMERA_FIELDS: tuple[str, ...] = (
    "focal_length_mm",
    "pixel_pitch_um",
    "principal_point_x_px",
    "principal_point_y_px",
    "image_width_px",
    "image_height_px",
    *DISTORTION_NAMES,
)
#: The table field of each estimable parameter (f is the focal length in mm).
ESTIMATE_FIELD: dict[str, str] = {
    "f": "focal_length_mm",
    "x0": "principal_point_x_px",
    "y0": "principal_point_y_px",
    **{k: k for k in DISTORTION_NAMES},
}
#: 1-sigma prior of each estimable parameter, in :data:`ESTIMATE_NAMES` order (f, x0, y0, k1..s2),
#: parameter units; NaN or 0 = unknown (cold-start prior).
SIGMA_FIELDS: tuple[str, ...] = tuple(f"sigma_{ESTIMATE_FIELD[name]}" for name in ESTIMATE_NAMES)
#: Field order of the table.
PARAM_FIELDS: tuple[str, ...] = CAMERA_FIELDS + SIGMA_FIELDS
N_FIELDS = len(PARAM_FIELDS)
#: Index of the first sigma field.
SIGMA_OFFSET = len(CAMERA_FIELDS)
#: Wire and storage dtype of one value.
TABLE_DTYPE = np.dtype("<f4")
TABLE_BYTES = N_FIELDS * TABLE_DTYPE.itemsize


class TableError(ValueError):
    """A byte string that is not a parameter table (wrong length)."""


def encode_table(values: Sequence[float] | np.ndarray) -> bytes:
    """N_FIELDS values in :data:`PARAM_FIELDS` order -> TABLE_BYTES bytes (each rounded to float32)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (N_FIELDS,):
        raise TableError(f"expected {N_FIELDS} values, got shape {arr.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # an out-of-range value becomes inf, refused by validation
        return arr.astype(TABLE_DTYPE).tobytes()


def decode_table(data: bytes | bytearray | memoryview) -> np.ndarray:
    """TABLE_BYTES bytes -> float32 array of the N_FIELDS values (a copy, native byte order)."""
    if len(data) != TABLE_BYTES:
        raise TableError(f"a parameter table is {TABLE_BYTES} bytes, got {len(data)}")
    return np.frombuffer(bytes(data), dtype=TABLE_DTYPE).astype(np.float32)


def table_crc(data: bytes | bytearray | memoryview) -> int:
    """CRC-32 of a parameter set (its TABLE_BYTES table bytes)."""
    if len(data) != TABLE_BYTES:
        raise TableError(f"a parameter table is {TABLE_BYTES} bytes, got {len(data)}")
    return crc32(data)


def table_from_mapping(values: Mapping[str, float]) -> bytes:
    """Table bytes from a mapping keyed by :data:`PARAM_FIELDS` (missing distortion keys are 0, missing sigmas NaN =
    unknown)."""
    return encode_table([float(values.get(name, math.nan if name in SIGMA_FIELDS else 0.0)) for name in PARAM_FIELDS])


def table_to_mapping(data: bytes | bytearray | memoryview) -> dict[str, float]:
    """Field name -> value (Python float holding the exact float32 value)."""
    return {name: float(v) for name, v in zip(PARAM_FIELDS, decode_table(data), strict=True)}


def camera_fields_from_file(data: Mapping) -> dict[str, float]:
    """A camera parameter-file object (``focal_length_mm``, ``pixel_pitch_um``, ``principal_point_px`` [x, y],
    ``image_size_px`` [w, h], ``distortion`` {k1..s2}) -> its :data:`CAMERA_FIELDS` values (missing distortion
    keys are 0)."""
    (x0, y0), (width, height) = data["principal_point_px"], data["image_size_px"]
    distortion = data.get("distortion") or {}
    return {
        "focal_length_mm": float(data["focal_length_mm"]),
        "pixel_pitch_um": float(data["pixel_pitch_um"]),
        "principal_point_x_px": float(x0),
        "principal_point_y_px": float(y0),
        "image_width_px": float(width),
        "image_height_px": float(height),
        **{k: float(distortion.get(k, 0.0)) for k in DISTORTION_NAMES},
    }


def camera_file_from_fields(values: Mapping[str, float]) -> dict:
    """:data:`CAMERA_FIELDS` values -> the camera parameter-file object (inverse of :func:`camera_fields_from_file`).
    An image size that is a whole number becomes an int; any other value is kept as it is, for the reader's
    validation to name."""

    def size(v: float) -> int | float:
        return int(v) if math.isfinite(v) and v == int(v) else v

    return {
        "focal_length_mm": values["focal_length_mm"],
        "pixel_pitch_um": values["pixel_pitch_um"],
        "principal_point_px": [values["principal_point_x_px"], values["principal_point_y_px"]],
        "image_size_px": [size(values["image_width_px"]), size(values["image_height_px"])],
        "distortion": {k: values[k] for k in DISTORTION_NAMES},
    }
