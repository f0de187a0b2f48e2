"""The bench report's PNG plots: residual fields before/after calibration, the onboard estimator's convergence
against its own 1-sigma, and the focal-length drift it tracks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostlink.mission.config import drift_amplitude_um, drift_first_frame
from hostlink.mission.summary import BenchRun, estimate_rows, rms, tracking_text, truth_focal_mm

#: Resolution of the saved figures [dots per inch].
PLOT_DPI = 110


def write_plots(out: Path, run: BenchRun, summary: dict) -> list[Path]:
    """Write the four PNG plots of ``run`` into ``out``; returns their paths."""
    from hostlink.calibration.plots import agg_pyplot
    from hostlink.files.atomic import save_figure

    paths = residual_plots(out, run)
    plt = agg_pyplot()
    for name, draw in (("estimator-convergence.png", _convergence_figure), ("drift-tracking.png", _drift_figure)):
        fig = draw(plt, run, summary)
        fig.text(0.01, 0.005, CAPTIONS[name], fontsize=8, wrap=True, va="bottom")
        fig.tight_layout(rect=(0, 0.07 if name == "estimator-convergence.png" else 0.12, 1, 1))
        save_figure(out / name, fig, dpi=PLOT_DPI)
        plt.close(fig)
        paths.append(out / name)
    return paths


#: What each bench figure says under the plot: how to read it and what to do about it.
CAPTIONS = {
    "estimator-convergence.png": (
        "Solid: the onboard estimate's error against the simulation's truth; dotted: the estimator's own 1-sigma. "
        "The solid line should wander at or below the dotted one: far above it, the estimator is overconfident "
        "(check --noise-px against the real centroid noise); after the upload (dashed) it restarts from the "
        "uploaded set's sigma, not from the cold-start prior."
    ),
    "drift-tracking.png": (
        "Black: the true focal length; blue: the onboard estimate and its 1-sigma band. The band should contain "
        "the black line about two thirds of the time; a blue line lagging the black one means the focal random "
        "walk is too small for this drift (the sensor switches it on when it detects a drift; `hostlink replay "
        "--focal-walk-um` sets it for a replay)."
    ),
}


def residual_plots(out: Path, run: BenchRun) -> list[Path]:
    """Mean residual per detector cell with the nominal and with the calibrated camera."""
    from hostlink.calibration.bundle import residuals
    from hostlink.calibration.plots import AFTER_CAPTION, BEFORE_CAPTION, residual_field_png
    from hostlink.calibration.report import fitted_attitudes

    data, nominal, outcome = run.data, run.nominal, run.outcome
    theta0 = nominal.model_vector()
    paths = []
    for name, e, label, caption in (
        (
            "residuals-before.png",
            residuals(data, theta0, fitted_attitudes(data, theta0)),
            "nominal camera",
            BEFORE_CAPTION,
        ),
        ("residuals-after.png", residuals(data, outcome.theta, outcome.attitudes), "calibrated camera", AFTER_CAPTION),
    ):
        title = f"Mean residual per cell, {label} (RMS {rms(np.linalg.norm(e, axis=1)):.4f} px)"
        residual_field_png(out / name, data.x_px, data.y_px, e, nominal.image_size_px, title, caption)
        paths.append(out / name)
    return paths


def _convergence_figure(plt, run: BenchRun, summary: dict):  # noqa: ARG001 - one signature for every figure
    """|estimate - truth| of f, x0, y0 against the estimator's own 1-sigma, both phases."""
    cfg, truth = run.cfg, run.cfg.camera
    cal, drift = estimate_rows(run.cal_estimates), estimate_rows(run.drift_estimates)
    f_true = np.concatenate([truth_focal_mm(run.cal_sim), truth_focal_mm(run.drift_sim)])
    frames_true = np.arange(f_true.size) + int(run.cal_sim.session.frame[0])
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for ax, key, sig, true_val, label_unit, scale in (
        (axes[0], "f_mm", "sigma_f_mm", None, "|f error| [um]", 1000.0),
        (axes[1], "x0_px", "sigma_x0_px", truth.principal_point_px[0], "|x0 error| [px]", 1.0),
        (axes[2], "y0_px", "sigma_y0_px", truth.principal_point_px[1], "|y0 error| [px]", 1.0),
    ):
        for rows, colour, label in (
            (cal, "tab:orange", "cold start from nominal"),
            (drift, "tab:blue", "restarted from the uploaded set"),
        ):
            if rows["frame"].size == 0:
                continue
            ref = np.interp(rows["frame"], frames_true, f_true) if key == "f_mm" else true_val
            ax.semilogy(rows["frame"], np.abs(rows[key] - ref) * scale, color=colour, label=f"|error|, {label}")
            ax.semilogy(rows["frame"], rows[sig] * scale, color=colour, ls=":", label=f"1-sigma, {label}")
        ax.axvline(cfg.cal_frames, color="grey", ls="--", lw=0.8)
        ax.set_ylabel(label_unit)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_title(
        "Onboard recursive estimator: error against truth and its own 1-sigma (dashed: upload)", fontsize=10
    )
    if axes[0].get_legend_handles_labels()[0]:  # nothing to label when the sensor gave no estimate
        axes[0].legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("frame")
    return fig


def _drift_figure(plt, run: BenchRun, summary: dict):
    """The true focal length through the drift phase and the onboard estimate with its 1-sigma band [um]."""
    cfg, drift = run.cfg, estimate_rows(run.drift_estimates)
    f_drift_true = truth_focal_mm(run.drift_sim)
    fr = np.arange(f_drift_true.size) + drift_first_frame(cfg) + int(run.drift_sim.session.frame[0])  # frame counter
    f_ref = cfg.camera.focal_length_mm
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.plot(fr, (f_drift_true - f_ref) * 1000.0, color="k", lw=1.2, label="true focal length")
    if drift["frame"].size:
        ax.plot(drift["frame"], (drift["f_mm"] - f_ref) * 1000.0, color="tab:blue", label="onboard estimate")
        ax.fill_between(
            drift["frame"],
            (drift["f_mm"] - drift["sigma_f_mm"] - f_ref) * 1000.0,
            (drift["f_mm"] + drift["sigma_f_mm"] - f_ref) * 1000.0,
            color="tab:blue",
            alpha=0.2,
            label="estimate 1-sigma",
        )
    amplitude_um = drift_amplitude_um(cfg)
    ax.set_title(f"Thermal focal-length drift: {amplitude_um:g} um amplitude; {tracking_text(summary)}", fontsize=10)
    ax.set_xlabel("frame")
    ax.set_ylabel(f"focal length - {f_ref:g} mm [um]")
    ax.legend(fontsize=8)
    return fig
