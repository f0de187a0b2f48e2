"""Camera parameter files (docs/file-formats.md): load, validate, save; the parameter files shipped with the package are
read by name (``builtin:seed004_nominal``, ``builtin:seed004_camera``).

Validation itself lives in ``onboard.params`` so that the host and the sensor refuse a set for the same reason.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import json_text, write_json, write_text
from onboard.params import CameraParams, ParameterError, params_from_dict, params_to_dict
from onboard.prior import sigma_from_dict

#: Parameter files shipped with the package (``hostlink/data``), wherever it is installed.
DATA_DIR = Path(__file__).resolve().parent.parent / "data"
#: ``builtin:NAME`` names the package's parameter file ``NAME.json`` wherever a parameter file is read.
BUILTIN_PREFIX = "builtin:"


def data_file(name: str) -> Path:
    """Path of a file shipped with the package in ``hostlink/data`` (``seed004_camera.json``: seed 004's simulated
    camera; ``seed004_nominal.json``: its design nominal), wherever the package is installed."""
    return DATA_DIR / name


def builtin_names() -> tuple[str, ...]:
    """The names ``builtin:NAME`` accepts: the parameter files shipped with the package."""
    return tuple(sorted(p.stem for p in DATA_DIR.glob("*.json")))


def params_path(path: str | Path) -> Path:
    """Where a parameter file is: ``builtin:NAME`` is the package's ``NAME.json`` (an unknown name is a one-line
    :class:`UserError` listing the known ones); anything else is a path."""
    text = str(path)
    if not text.startswith(BUILTIN_PREFIX):
        return Path(path)
    name = text[len(BUILTIN_PREFIX) :].removesuffix(".json")
    if name not in builtin_names():
        known = ", ".join(BUILTIN_PREFIX + n for n in builtin_names())
        raise UserError(f"{text}: no such built-in parameter file (known: {known})")
    return data_file(name + ".json")


def load_params(path: str | Path) -> CameraParams:
    """Read and validate a camera parameter file (a path, or ``builtin:NAME`` for one shipped with the package);
    any problem is a one-line :class:`UserError` naming the field."""
    return load_params_with_extras(path)[0]


def load_params_with_extras(path: str | Path, validate: bool = True) -> tuple[CameraParams, dict]:
    """As :func:`load_params`, also returning the file's whole JSON object (for ``sigma`` and other extras).
    ``validate=False`` checks the form only, not the ranges (``onboard.params.params_from_dict``)."""
    path = params_path(path)
    return params_from_text(_read_text(path), str(path), validate)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise UserError(f"{path}: no such file") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not a JSON text file ({exc.reason} at byte {exc.start})") from None


def params_from_text(text: str, source: str = "<text>", validate: bool = True) -> tuple[CameraParams, dict]:
    """A parameter file's text -> (validated CameraParams, the whole JSON object); ``source`` names it in errors.
    Any problem with the text (not JSON, nested too deeply, an integer too long to convert, a field missing, of the
    wrong type or out of range) is a one-line :class:`UserError`."""
    data = parse_json(text, source)
    try:
        return params_from_dict(data, validate), data
    except ParameterError as exc:
        raise UserError(f"{source}: {exc}") from None


def parse_json(text: str, source: str = "<text>") -> object:
    """JSON text -> Python object (NaN and +-Infinity read as floats); a malformed text is a one-line
    :class:`UserError` naming ``source``."""
    try:
        return json.loads(text, parse_constant=_json_constant)
    except json.JSONDecodeError as exc:
        raise UserError(f"{source}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    except RecursionError:  # Python's parser recurses once per level of [ or {
        raise UserError(f"{source}: not valid JSON for this reader (arrays or objects nested too deeply)") from None
    except ValueError:  # the only other ValueError json raises: an integer of more digits than Python converts
        limit = sys.get_int_max_str_digits()
        raise UserError(f"{source}: not valid JSON for this reader (an integer of more than {limit} digits)") from None


def load_params_with_sigma(path: str | Path, validate: bool = True) -> tuple[CameraParams, np.ndarray]:
    """A camera parameter file and its ``sigma`` object as 10 values in ESTIMATE_NAMES order (parameter units, NaN =
    unknown; ``onboard.prior.sigma_from_dict``). ``validate=False`` reads both without the range checks (for
    letting a sensor's own checks refuse them). Any problem is a one-line :class:`UserError`."""
    path = params_path(path)
    return params_with_sigma_from_text(_read_text(path), str(path), validate)


def params_with_sigma_from_text(
    text: str, source: str = "<text>", validate: bool = True
) -> tuple[CameraParams, np.ndarray]:
    """As :func:`load_params_with_sigma`, from the file's text (``source`` names it in errors)."""
    params, data = params_from_text(text, source, validate)
    try:
        return params, sigma_from_dict(data.get("sigma"), validate=validate)
    except ParameterError as exc:
        raise UserError(f"{source}: {exc}") from None


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
    """Write a parameter file atomically (:func:`hostlink.files.atomic.write_json`), so a crash never leaves half
    a file."""
    write_json(path, params_json(params, extras))


def emit_param_file(data: dict, out: str | Path | None = None) -> None:
    """Print a parameter-file object as JSON on stdout and, with ``out``, also write it there (atomically; first, so
    that a file that cannot be written leaves nothing on stdout to be taken for a result)."""
    text = json_text(data)
    if out:
        write_text(out, text)
    sys.stdout.write(text)


# ---------------------------------------------------------------------------------------------------------------
# calibration status (issue 31): a result file says whether it may be used as a camera

#: The ``status`` of a parameter file written by ``hostlink calibrate`` or ``hostlink replay``: ``converged`` (a
#: usable calibration), ``not_converged`` (the fit or the recursive estimator did not converge) or ``failed`` (it
#: converged to a result that must not be used, e.g. most stars rejected). ``status_reason`` says why.
STATUS_CONVERGED = "converged"
STATUS_NOT_CONVERGED = "not_converged"
STATUS_FAILED = "failed"
STATUSES = (STATUS_CONVERGED, STATUS_NOT_CONVERGED, STATUS_FAILED)


def status_fields(status: str, reason: str | None = None) -> dict:
    """The parameter file's status keys: ``status`` (one of :data:`STATUSES`) and ``status_reason`` (null when
    converged, else one line saying why)."""
    if status not in STATUSES:
        raise ValueError(f"unknown calibration status {status!r} (expected one of {', '.join(STATUSES)})")
    return {"status": status, "status_reason": reason}


def file_status(data: dict) -> tuple[str | None, str | None]:
    """A parameter file's (status, reason). A file with a ``status`` key says it; a file without one (a design
    nominal, a hand-written set, a file from before issue 31) has status None, unless it carries the older markers of
    a failed calibration: ``failed`` (the reason, written by ``calibrate --keep-failed``) or ``converged: false``.
    An unknown status value is a :class:`UserError` (never read as converged)."""
    status = data.get("status")
    if status is None:
        if isinstance(data.get("failed"), str):
            return STATUS_FAILED, data["failed"]
        if data.get("converged") is False:
            return STATUS_NOT_CONVERGED, "converged: false (a file from before the status key)"
        return None, None
    if status not in STATUSES:
        raise UserError(f"status: expected one of {', '.join(STATUSES)}, got {status!r}")
    reason = data.get("status_reason")
    return status, reason if isinstance(reason, str) else None


def upload_refusal(data: dict, source: str) -> str | None:
    """Why the parameter file ``source`` (its JSON object ``data``) must not be uploaded to a sensor, in one line,
    or None: a calibration that failed or did not converge is never uploaded (docs/interfaces.md)."""
    status, reason = file_status(data)
    if status is None or status == STATUS_CONVERGED:
        return None
    what = "failed" if status == STATUS_FAILED else "did not converge"
    because = f": {reason}" if reason else ""
    return (
        f"{source}: refused, the calibration in this file {what} (status {status}{because}); nothing was sent to the "
        "sensor"
    )


def load_params_for_upload(path: str | Path, validate: bool = True) -> tuple[CameraParams, np.ndarray]:
    """As :func:`load_params_with_sigma`, for sending to a sensor: a file whose calibration failed or did not
    converge (:func:`upload_refusal`) is a one-line :class:`UserError`, raised before any link is opened. The
    status is checked whatever ``validate`` says (the range checks are a separate matter)."""
    path = params_path(path)
    text = _read_text(path)
    data = parse_json(text, str(path))
    if isinstance(data, dict):
        refusal = upload_refusal(data, str(path))
        if refusal:
            raise UserError(refusal)
    return params_with_sigma_from_text(text, str(path), validate)
