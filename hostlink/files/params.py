"""Camera parameter files (INTERFACES.md): load, validate, save.

Validation itself lives in ``onboard.params`` so that the host and the sensor refuse a set for the same reason.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from onboard.params import CameraParams, ParameterError, params_from_dict, params_to_dict
from onboard.prior import sigma_from_dict


def load_params(path: str | Path) -> CameraParams:
    """Read and validate a camera parameter file; any problem is a one-line :class:`UserError` naming the field."""
    return load_params_with_extras(path)[0]


def load_params_with_extras(path: str | Path, validate: bool = True) -> tuple[CameraParams, dict]:
    """As :func:`load_params`, also returning the file's whole JSON object (for ``sigma`` and other extras).
    ``validate=False`` checks the form only, not the ranges (``onboard.params.params_from_dict``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not a JSON text file ({exc.reason} at byte {exc.start})") from None
    try:
        data = json.loads(text, parse_constant=_json_constant)
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    try:
        return params_from_dict(data, validate), data
    except ParameterError as exc:
        raise UserError(f"{path}: {exc}") from None


def load_params_with_sigma(path: str | Path, validate: bool = True) -> tuple[CameraParams, np.ndarray]:
    """A camera parameter file and its ``sigma`` object as 10 values in ESTIMATE_NAMES order (parameter units, NaN =
    unknown; ``onboard.prior.sigma_from_dict``). ``validate=False`` reads both without the range checks (for
    letting a sensor's own checks refuse them). Any problem is a one-line :class:`UserError`."""
    params, data = load_params_with_extras(path, validate)
    try:
        return params, sigma_from_dict(data.get("sigma"), validate=validate)
    except ParameterError as exc:
        raise UserError(f"{path}: {exc}") from None


def _json_constant(name: str) -> float:
    # NaN / Infinity are not JSON, but Python writes them; read them so validation can name the field.
    return {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}[name]


def params_json(params: CameraParams, extras: dict | None = None) -> dict:
    """The JSON object of a parameter file, with optional extra keys (``sigma``, ``method``, statistics...)."""
    data = params_to_dict(params)
    if extras:
        for key, value in extras.items():
            if key in data:
                raise ValueError(f"extra key {key!r} would overwrite a camera parameter")
            data[key] = value
    return data


def save_params(path: str | Path, params: CameraParams, extras: dict | None = None) -> None:
    """Write a parameter file atomically (temporary file, then rename), so a crash never leaves half a file."""
    path = Path(path)
    data = params_json(params, extras)
    tmp = path.with_name(path.name + ".tmp")
    try:
        if path.parent and not path.parent.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        raise UserError(f"{path}: cannot write ({exc.strerror})") from None


def emit_param_file(data: dict, out: str | Path | None = None) -> None:
    """Print a parameter-file object as JSON on stdout and, with ``out``, also write it there (atomically)."""
    import sys

    text = json.dumps(data, indent=2) + "\n"
    sys.stdout.write(text)
    if out:
        path = Path(out)
        tmp = path.with_name(path.name + ".tmp")
        try:
            tmp.write_text(text, encoding="utf-8")
            tmp.replace(path)
        except OSError as exc:
            raise UserError(f"{path}: cannot write ({exc.strerror})") from None
