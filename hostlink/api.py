"""The public Python API of the host (ARCHITECTURE.md ``hostlink/api``): one import for the whole job.

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

Files (INTERFACES.md formats; every write is atomic):
    :func:`read_session`, :func:`read_session_chunks` (a session of any length, or several files, in chunks of whole
    frames), :func:`concatenate_sessions`, :func:`write_session`, :class:`SessionWriter` (CSV, or Parquet for
    ``*.parquet``), :func:`load_params`,
    :func:`load_params_with_sigma`, :func:`save_params`, :func:`read_truth`, :func:`write_truth`,
    :func:`write_attitudes`, :func:`write_trace`, :class:`TraceWriter`, :func:`read_trace`, :func:`data_file` (the
    camera files shipped with
    the package; ``load_params("builtin:NAME")`` reads one by name).
Sky:
    :func:`simulate` (a session of the real sky through a true camera, with its truth), :func:`session_references`
    (THE reference directions of a session's rows), :func:`solve_attitudes` (the attitude of every frame).
Images:
    :func:`centroid_images` (star centroids from FITS/TIFF/PNG images into a session of unidentified stars, with
    :class:`CentroidOptions`, :class:`TimeOptions` and one :class:`FrameReport` per image in a
    :class:`CentroidResult`), :func:`centroid_pixels` (one image array), :func:`read_image` (THE image reader),
    :func:`centroid_crb_px` (the Cramer-Rao bound of a centroid), :func:`render_stars` / :func:`render_frame` with
    :class:`RenderConfig` (images of simulated stars with known truth, for tests),
    :func:`identify_session` (lost-in-space identification of a session's unidentified stars against Hipparcos,
    with :class:`Identification` and one :class:`FrameIdentity` per frame: attitude, parity, scale).
Calibration:
    :func:`calibrate_session` (batch ground calibration), :func:`calibrate_archive` (the same for sessions of any
    length: files, globs, Parquet, chunk by chunk in bounded memory, optionally on a Dask cluster),
    :func:`result_extras`, :func:`cross_validate` (a calibration judged on stars held out of its fit: k-fold
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
Emulated sensor and the bench:
    :class:`EmulatorProcess` (``hostlink emulate`` as a child process), :func:`build_sensor` (the firmware and its
    frame source, in process), :func:`run_bench` with :class:`BenchConfig` (the whole mission end to end),
    :func:`design_nominal` (a camera's design values: what is known of it before calibration).
"""

from __future__ import annotations

from hostlink.calibration.holdout import CrossValidation, cross_validate
from hostlink.calibration.replay import (
    ReplayResult,
    estimate_extras,
    replay_chunks,
    replay_config,
    replay_prior,
    replay_session,
)
from hostlink.calibration.run import METHODS, CalibrationOutcome, calibrate_archive, calibrate_session, result_extras
from hostlink.emulator.process import EmulatorProcess
from hostlink.emulator.setup import build_sensor
from hostlink.errors import LinkError, SensorRefused, UserError
from hostlink.files.attitude import write_attitudes
from hostlink.files.params import data_file, load_params, load_params_with_sigma, save_params
from hostlink.files.session import (
    Session,
    SessionWriter,
    concatenate_sessions,
    read_session,
    read_session_chunks,
    write_session,
)
from hostlink.files.trace import TraceWriter, read_trace, write_trace
from hostlink.files.truth import read_truth, write_truth
from hostlink.images.centroid import (
    CentroidOptions,
    CentroidResult,
    FrameReport,
    TimeOptions,
    centroid_crb_px,
    centroid_images,
    centroid_pixels,
)
from hostlink.images.identify import FrameIdentity, Identification, identify_iteratively, identify_session
from hostlink.images.read import RawImage, read_image
from hostlink.links import Link, open_link
from hostlink.links.base import CommandRefused
from hostlink.links.operations import (
    ActiveParams,
    EstimatePoll,
    StreamResult,
    UploadMismatch,
    UploadResult,
    accept_estimate,
    estimate_record,
    float32_equal,
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
from hostlink.mission.run import run_bench
from hostlink.portkit.costs import cost_table, cost_table_text
from hostlink.portkit.export_c import write_c as export_c
from hostlink.portkit.vectors import write_vectors
from hostlink.sky.attitude import REFRACTION_MODES, SessionAttitudes, solve_attitudes
from hostlink.sky.references import SessionReferences, session_references
from hostlink.sky.render import RenderConfig, RenderedFrame, render_frame, render_stars
from hostlink.sky.simulate import SimConfig, SimResult, simulate
from onboard.params import ESTIMATE_NAMES, CameraParams, Distortion
from onboard.recursive import RecursiveConfig
from onboard.site import Site, Weather
from protocol.messages import Estimate

__all__ = [
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
    "session_references",
    "simulate",
    "solve_attitudes",
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
    "export_c",
    "write_vectors",
    # emulator and bench
    "EmulatorProcess",
    "build_sensor",
    "design_nominal",
    "run_bench",
]
