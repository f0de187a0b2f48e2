"""The parameter table: how a camera parameter set travels (every transport) and is stored (sensor banks).

A table is 13 IEEE-754 float32 values, little-endian, in :data:`PARAM_FIELDS` order (52 bytes). The fields are the
keys of a camera parameter file (shared/spec/CAMERA_MODEL.md), flattened; ``image_size_px`` travels as float32 too
(exact for any size below 2**24). The CRC of a set is :func:`protocol.crc.crc32` over those 52 bytes.

"Equal to float32" (INTERFACES.md, ``hostlink upload``) means: every file value rounded to float32 (round to
nearest even, as numpy does) equals the value the sensor reports, bit for bit.

Pure: bytes in, values out. The mapping to ``onboard.params.CameraParams`` lives in ``onboard.banks`` (protocol
imports nothing from onboard).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from protocol.crc import crc32

#: Field order of the table. Names are those of the parameter file (``principal_point_px``/``image_size_px`` split).
PARAM_FIELDS: tuple[str, ...] = (
    "focal_length_mm",
    "pixel_pitch_um",
    "principal_point_x_px",
    "principal_point_y_px",
    "image_width_px",
    "image_height_px",
    "k1",
    "k2",
    "k3",
    "p1",
    "p2",
    "s1",
    "s2",
)
N_FIELDS = len(PARAM_FIELDS)
#: Wire and storage dtype of one value.
TABLE_DTYPE = np.dtype("<f4")
TABLE_BYTES = N_FIELDS * TABLE_DTYPE.itemsize


class TableError(ValueError):
    """A byte string that is not a parameter table (wrong length)."""


def encode_table(values: Sequence[float] | np.ndarray) -> bytes:
    """13 values in :data:`PARAM_FIELDS` order -> 52 bytes (each rounded to float32)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (N_FIELDS,):
        raise TableError(f"expected {N_FIELDS} values, got shape {arr.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # an out-of-range value becomes inf, refused by validation
        return arr.astype(TABLE_DTYPE).tobytes()


def decode_table(data: bytes | bytearray | memoryview) -> np.ndarray:
    """52 bytes -> float32 array of the 13 values (a copy, native byte order)."""
    if len(data) != TABLE_BYTES:
        raise TableError(f"a parameter table is {TABLE_BYTES} bytes, got {len(data)}")
    return np.frombuffer(bytes(data), dtype=TABLE_DTYPE).astype(np.float32)


def table_crc(data: bytes | bytearray | memoryview) -> int:
    """CRC-32 of a parameter set (its 52 table bytes)."""
    if len(data) != TABLE_BYTES:
        raise TableError(f"a parameter table is {TABLE_BYTES} bytes, got {len(data)}")
    return crc32(data)


def table_from_mapping(values: Mapping[str, float]) -> bytes:
    """Table bytes from a mapping keyed by :data:`PARAM_FIELDS` (missing distortion keys are 0)."""
    return encode_table([float(values.get(name, 0.0)) for name in PARAM_FIELDS])


def table_to_mapping(data: bytes | bytearray | memoryview) -> dict[str, float]:
    """Field name -> value (Python float holding the exact float32 value)."""
    return {name: float(v) for name, v in zip(PARAM_FIELDS, decode_table(data), strict=True)}
