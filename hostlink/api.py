"""The public Python API of the host (docs/architecture.md ``hostlink/api``): one import for the whole job.

    from hostlink import api

Everything a command does is one call here; the commands (``hostlink/commands``) only parse their options, call
these functions and print. The names below are the documented surface: modules behind them may move, these names
stay. docs/api.md walks through a whole session (simulate, calibrate, replay, attitude, emulator, upload, read back).

Units: angles in degrees where a name ends in ``_deg``, radians in ``_rad``, arcseconds in ``_arcsec``; pixels
``_px``; focal length in mm (``focal_length_mm``); times are ISO 8601 UTC strings or two-part Julian dates (UTC);
``dut1_s`` = UT1 - UTC [s]. Vectors are float64 numpy arrays unless a ``dtype``/``precision`` says otherwise.

Errors: every failure a user can cause raises :class:`UserError` with a one-line message (bad input, a result that
would be wrong, e.g. not converged or a centroid off the detector); :class:`LinkError` (a subclass) when the link
to a sensor fails; :class:`SensorRefused` / :class:`CommandRefused` when the sensor refuses a command and says why;
:class:`UploadMismatch` when a read-back differs from what was uploaded.

Files (docs/file-formats.md formats; every write is atomic):
    :func:`read_session`, :func:`read_session_chunks` (a session of any length, or several files, in chunks of whole
    frames), :func:`concatenate_sessions`, :func:`write_session`, :class:`SessionWriter` (CSV, or Parquet for
    ``*.parquet``), :func:`load_params`,
    :func:`load_params_with_sigma`, :func:`load_params_for_upload` (refuses a failed or unconverged calibration),
    :func:`params_file_status`, :func:`save_params`, :func:`read_truth`, :func:`write_truth`,
    :func:`write_attitudes`, :func:`write_trace`, :class:`TraceWriter`, :func:`read_trace`, :func:`data_file` (the
    camera files shipped with
    the package; ``load_params("builtin:NAME")`` reads one by name).
Sky:
    :func:`simulate` (a session of the real sky through a true camera, with its truth; :func:`simulate_chunks`
    the same chunk by chunk as :class:`SimChunk` s, :func:`write_simulation` straight to its files in bounded
    memory), :func:`session_references`
    (THE reference directions of a session's rows), :func:`solve_attitudes` (the attitude of every frame), in other
    forms: :func:`attitude_quaternion` (scalar first), :func:`boresight_radec_roll`, :func:`attitude_records` (the
    rows of ATTITUDE.csv as objects), and as FITS WCS: :func:`sip_model` (the camera's distortion as SIP, with its
    fit errors), :func:`wcs_directory` (its folder, checked first), :func:`write_wcs_headers` (one TAN-SIP header per
    frame); :func:`read_attitude_matrices` reads scripted attitudes (c11..c33) back.
Images:
    :func:`centroid_images` (star centroids from FITS/TIFF/PNG images into a session of unidentified stars, with
    :class:`CentroidOptions`, :class:`TimeOptions` and one :class:`FrameReport` per image in a
    :class:`CentroidResult`), :func:`centroid_pixels` (one image array), :func:`read_image` (THE image reader),
    :func:`centroid_crb_px` (the Cramer-Rao bound of a centroid), :func:`render_stars` / :func:`render_frame` with
    :class:`RenderConfig` (images of simulated stars with known truth, for tests),
    :func:`identify_session` (lost-in-space identification of a session's unidentified stars against Hipparcos,
    with :class:`Identification` and one :class:`FrameIdentity` per frame: attitude, parity, scale),
    :func:`prepare_cache` (a camera's catalogue index, pattern database and pair table built beforehand, a
    :class:`PairCache` to pass to many identifications).
Calibration:
    :func:`calibrate_session` (batch ground calibration), :func:`calibrate_archive` (the same for sessions of any
    length: files, globs, Parquet, chunk by chunk in bounded memory, optionally on a Dask cluster),
    :func:`result_extras`, :func:`noise_model_text` (the noise model's line; :data:`NOISE_MODELS`),
    :func:`cross_validate` (a calibration judged on stars held out of its fit: k-fold
    over the frames, :class:`CrossValidation`), :func:`replay_session` (the
    onboard recursive estimator over a session, as the sensor runs it), :func:`replay_chunks` (the same over chunks,
    its trace streamed), :func:`replay_config`, :func:`replay_prior`,
    :func:`estimate_extras`.
Sensor links (serial, CAN, Modbus; real or emulated, chosen by one link string):
    :func:`open_link`, :func:`stream_frames`, :func:`record_session`, :func:`poll_estimate`, :func:`poll_estimates`,
    :func:`estimate_record`, :func:`safe_upload`, :func:`read_active_params`, :func:`read_estimate`,
    :func:`accept_estimate`, :func:`params_float32_dict`, :func:`float32_equal`.
Port kit (docs/port-kit.md):
    :func:`export_c` (C99 headers and source of the wire protocol), :func:`write_vectors` (golden test vectors of the
    onboard functions, float32 and fixed point, with tolerances), :func:`cost_table` / :func:`cost_table_text`
    (operations and memory per frame at N stars).
Ground systems (docs/ground-systems.md):
    :func:`export_ground` (an OpenC3 COSMOS target and an XTCE 1.2 document of every message, from the one table).
The judge (scoring a calibration against a known truth; the tests and benchmarks use the same functions):
    :func:`synthetic_session` (random star fields through a known camera, exact truth, :class:`SyntheticSession`),
    :func:`make_frames` / :func:`synth_frames` / :func:`sky_frames` (the same frame by frame, for the recursive
    estimator), :func:`seed004_true_camera`, :func:`seed004_paper_start`; :func:`fisher_information` (the
    Cramer-Rao bound of a session, attitudes as nuisance), :func:`validation_residual_px` /
    :func:`validation_residual_from_directions_px` (accuracy over the detector, [px]), :func:`validation_jacobian`,
    :func:`crb_validation_px` (its bound), :func:`grid_points`, :func:`interstar_frame_information`,
    :func:`interstar_information`, :func:`interstar_batch_ml` (the onboard measurement model's bound and batch
    estimate), :func:`attitude_covariance` (an attitude's bound), :func:`rotation_angle_rad`.
Helpers the commands share (parsing and checking options, what they print):
    :func:`check_on_detector`, :func:`session_paths`, :func:`truth_path_for`, :func:`emit_param_file`,
    :func:`write_json`, :func:`write_rejected`, :func:`write_calibration_plots`, :func:`summary_table`,
    :func:`write_example`, :func:`progress_bar`, :func:`parse_estimate_names`, :func:`refined_mask`,
    :func:`refraction_mode`, :func:`precision_dtype`, :func:`seed004_config`, :func:`frames_to_session`,
    :func:`read_can_capture` (loaded on first use), :func:`parse_endpoint_options`, and the constants
    ``DISTORTION_NAMES``, ``DEFAULT_REJECT_ARCSEC``, ``PRECISIONS``, ``REFRACTION_MODELS``, ``ENDPOINTS``,
    ``WIRE_PX_FORMAT``, with :class:`EndpointOptions` and :class:`EstimatorBudget`.
Emulated sensor and the bench:
    :class:`EmulatorProcess` (``hostlink emulate`` as a child process), :func:`build_sensor` (the firmware and its
    frame source, in process), :func:`run_bench` with :class:`BenchConfig` (the whole mission end to end),
    :func:`design_nominal` (a camera's design values: what is known of it before calibration).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

# The names below are imported when first used (PEP 562 ``__getattr__`` at the end of this module), so that
# ``import hostlink.api`` costs milliseconds and pulls in no numpy, scipy or astropy (issue 31: a user who only uploads
# a file does not wait for the image stack). The import statements stay the one list of where each name lives: type
# checkers read them here, and :func:`_lazy_table` reads the same statements from this file's source.
if TYPE_CHECKING:
    from hostlink.calibration.chunked import estimated_session_rows
    from hostlink.calibration.crb import (
        attitude_covariance,
        crb_validation_px,
        fisher_information,
        grid_points,
        interstar_batch_ml,
        interstar_frame_information,
        interstar_information,
        rotation_angle_rad,
        validation_jacobian,
        validation_residual_from_directions_px,
        validation_residual_px,
    )
    from hostlink.calibration.floorfit import NOISE_MODELS, noise_model_text
    from hostlink.calibration.holdout import CrossValidation, cross_validate
    from hostlink.calibration.outcome import focal_hint
    from hostlink.calibration.plots import write_calibration_plots
    from hostlink.calibration.rejected import write_rejected
    from hostlink.calibration.replay import (
        ReplayResult,
        estimate_extras,
        precision_dtype,
        replay_chunks,
        replay_config,
        replay_prior,
        replay_session,
    )
    from hostlink.calibration.report import iterations_text
    from hostlink.calibration.run import (
        METHODS,
        CalibrationOutcome,
        calibrate_archive,
        calibrate_session,
        result_extras,
    )
    from hostlink.calibration.synthetic import (
        SyntheticSession,
        make_frames,
        seed004_paper_start,
        seed004_true_camera,
        sky_frames,
        synth_frames,
        synthetic_session,
    )
    from hostlink.emulator import ENDPOINTS
    from hostlink.emulator.process import EmulatorProcess
    from hostlink.emulator.sensor import EndpointOptions
    from hostlink.emulator.setup import build_sensor, parse_endpoint_options
    from hostlink.errors import LinkError, SensorRefused, UserError
    from hostlink.files.atomic import json_text, write_json
    from hostlink.files.attitude import attitude_records, read_attitude_matrices, write_attitudes
    from hostlink.files.params import (
        data_file,
        emit_param_file,
        load_params,
        load_params_for_upload,
        load_params_with_sigma,
        params_json,
        save_params,
    )
    from hostlink.files.params import file_status as params_file_status
    from hostlink.files.session import (
        Session,
        SessionWriter,
        check_on_detector,
        concatenate_sessions,
        read_session,
        read_session_chunks,
        session_paths,
        write_session,
    )
    from hostlink.files.trace import TraceWriter, read_trace, write_trace
    from hostlink.files.truth import read_truth, truth_path_for, write_truth
    from hostlink.files.wcs import wcs_directory, write_wcs_headers
    from hostlink.images.centroid import (
        CentroidOptions,
        CentroidResult,
        FrameReport,
        TimeOptions,
        centroid_crb_px,
        centroid_images,
        centroid_pixels,
    )
    from hostlink.images.identify import (
        MAX_ROUNDS,
        FrameIdentity,
        Identification,
        PairCache,
        identify_iteratively,
        identify_session,
        prepare_cache,
    )
    from hostlink.images.read import RawImage, read_image
    from hostlink.links import Link, open_link
    from hostlink.links.base import CommandRefused
    from hostlink.links.can_capture import read_can_capture
    from hostlink.links.operations import (
        WIRE_PX_FORMAT,
        ActiveParams,
        EstimatePoll,
        StreamResult,
        UploadMismatch,
        UploadResult,
        accept_estimate,
        estimate_record,
        float32_equal,
        frames_to_session,
        params_float32_dict,
        poll_estimate,
        poll_estimates,
        read_active_params,
        read_estimate,
        record_session,
        safe_upload,
        stream_frames,
    )
    from hostlink.mission.config import BenchConfig, design_nominal
    from hostlink.mission.example import write_example
    from hostlink.mission.run import run_bench
    from hostlink.mission.summary import summary_table
    from hostlink.mission.target_costs import TARGET_COST_FRAMES, target_costs
    from hostlink.portkit.costs import cost_table, cost_table_text
    from hostlink.portkit.export_c import write_c as export_c
    from hostlink.portkit.export_ground import write_ground as export_ground
    from hostlink.portkit.target_costs import format_reports as format_target_costs
    from hostlink.portkit.vectors import write_vectors
    from hostlink.progress import progress_bar
    from hostlink.sky.attitude import (
        SessionAttitudes,
        refraction_mode,
        solve_attitudes,
    )
    from hostlink.sky.attitude_choices import DEFAULT_REJECT_ARCSEC, PRECISIONS, REFRACTION_MODELS, REFRACTION_MODES
    from hostlink.sky.pointing import SipModel, attitude_quaternion, boresight_radec_roll, sip_model
    from hostlink.sky.references import SessionReferences, session_references
    from hostlink.sky.render import RenderConfig, RenderedFrame, render_frame, render_stars
    from hostlink.sky.simulate import (
        SimChunk,
        SimConfig,
        SimResult,
        seed004_config,
        simulate,
        simulate_chunks,
        write_simulation,
    )
    from onboard.firmware import EstimatorBudget
    from onboard.params import CameraParams, Distortion
    from onboard.prior import refined_mask
    from onboard.recursive import RecursiveConfig, parse_estimate_names
    from onboard.site import Site, Weather
    from protocol.messages import Estimate
    from protocol.names import DISTORTION_NAMES, ESTIMATE_NAMES
    from protocol.param_table import DISTORTION_UNITS

__all__ = [
    "estimated_session_rows",
    "DISTORTION_UNITS",
    "focal_hint",
    "iterations_text",
    "json_text",
    "params_json",
    # data
    "ActiveParams",
    "BenchConfig",
    "CalibrationOutcome",
    "CameraParams",
    "CentroidOptions",
    "CentroidResult",
    "Distortion",
    "ESTIMATE_NAMES",
    "Estimate",
    "EstimatePoll",
    "FrameIdentity",
    "FrameReport",
    "Identification",
    "Link",
    "METHODS",
    "REFRACTION_MODES",
    "RawImage",
    "RecursiveConfig",
    "RenderConfig",
    "RenderedFrame",
    "ReplayResult",
    "Session",
    "SessionAttitudes",
    "SessionReferences",
    "SimConfig",
    "SimResult",
    "Site",
    "StreamResult",
    "TimeOptions",
    "UploadResult",
    "Weather",
    # errors
    "CommandRefused",
    "LinkError",
    "SensorRefused",
    "UploadMismatch",
    "UserError",
    # files
    "SessionWriter",
    "TraceWriter",
    "data_file",
    "load_params",
    "load_params_with_sigma",
    "load_params_for_upload",
    "params_file_status",
    "read_session",
    "read_session_chunks",
    "concatenate_sessions",
    "read_trace",
    "read_truth",
    "save_params",
    "write_attitudes",
    "write_session",
    "write_trace",
    "write_truth",
    # images
    "centroid_crb_px",
    "centroid_images",
    "centroid_pixels",
    "read_image",
    "render_frame",
    "render_stars",
    # sky
    "identify_session",
    "identify_iteratively",
    "MAX_ROUNDS",
    "prepare_cache",
    "PairCache",
    "session_references",
    "simulate",
    "simulate_chunks",
    "write_simulation",
    "SimChunk",
    "solve_attitudes",
    "attitude_quaternion",
    "boresight_radec_roll",
    "attitude_records",
    "sip_model",
    "SipModel",
    "write_wcs_headers",
    "wcs_directory",
    "read_attitude_matrices",
    # calibration
    "calibrate_session",
    "calibrate_archive",
    "cross_validate",
    "CrossValidation",
    "estimate_extras",
    "replay_config",
    "replay_prior",
    "replay_session",
    "replay_chunks",
    "result_extras",
    "NOISE_MODELS",
    "noise_model_text",
    # links
    "accept_estimate",
    "estimate_record",
    "float32_equal",
    "open_link",
    "params_float32_dict",
    "poll_estimate",
    "poll_estimates",
    "read_active_params",
    "read_estimate",
    "record_session",
    "safe_upload",
    "stream_frames",
    # port kit
    "cost_table",
    "cost_table_text",
    "target_costs",
    "format_target_costs",
    "TARGET_COST_FRAMES",
    "export_c",
    "export_ground",
    "write_vectors",
    # emulator and bench
    "EmulatorProcess",
    "build_sensor",
    "design_nominal",
    "run_bench",
    # the judge
    "SyntheticSession",
    "attitude_covariance",
    "crb_validation_px",
    "fisher_information",
    "grid_points",
    "interstar_batch_ml",
    "interstar_frame_information",
    "interstar_information",
    "make_frames",
    "rotation_angle_rad",
    "seed004_paper_start",
    "seed004_true_camera",
    "sky_frames",
    "synth_frames",
    "synthetic_session",
    "validation_jacobian",
    "validation_residual_from_directions_px",
    "validation_residual_px",
    # helpers the commands share
    "DEFAULT_REJECT_ARCSEC",
    "DISTORTION_NAMES",
    "ENDPOINTS",
    "EndpointOptions",
    "EstimatorBudget",
    "PRECISIONS",
    "REFRACTION_MODELS",
    "WIRE_PX_FORMAT",
    "check_on_detector",
    "emit_param_file",
    "frames_to_session",
    "parse_endpoint_options",
    "parse_estimate_names",
    "precision_dtype",
    "progress_bar",
    "read_can_capture",
    "refined_mask",
    "refraction_mode",
    "seed004_config",
    "session_paths",
    "summary_table",
    "truth_path_for",
    "write_calibration_plots",
    "write_example",
    "write_json",
    "write_rejected",
]


def _lazy_table() -> dict[str, tuple[str, str]]:
    """Public name -> (module, attribute), from the ``from MODULE import NAME [as ALIAS]`` statements of this file's
    ``if TYPE_CHECKING:`` block (the one list of where each name lives)."""
    import ast
    from pathlib import Path

    tree = ast.parse(Path(__file__).read_text(encoding="utf-8"))
    table: dict[str, tuple[str, str]] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for stmt in node.body:
                if isinstance(stmt, ast.ImportFrom) and stmt.module:
                    for alias in stmt.names:
                        table[alias.asname or alias.name] = (stmt.module, alias.name)
    return table


_LAZY: dict[str, tuple[str, str]] | None = None


def __getattr__(name: str):  # noqa: ANN202 - PEP 562: the public names, imported on first use
    global _LAZY
    if _LAZY is None:
        _LAZY = _lazy_table()
    try:
        module, attribute = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    import importlib

    value = getattr(importlib.import_module(module), attribute)
    globals()[name] = value  # later uses are plain lookups
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
