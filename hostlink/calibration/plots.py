"""Figures of a calibration (matplotlib, Agg backend): the residual vector field and the convergence history."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostlink.files.atomic import save_figure

#: Cells per detector side of the binned residual field (each arrow is the mean residual of one cell).
FIELD_CELLS = 16


def agg_pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display): every figure the package saves uses it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def residual_field_png(
    path: Path,
    x_px: np.ndarray,
    y_px: np.ndarray,
    e_px: np.ndarray,
    image_size_px: tuple[int, int],
    title: str,
    caption: str | None = None,
) -> None:
    """Mean residual per cell of a 16 x 16 grid over the detector, as arrows; the scale is stated in the legend, and
    ``caption`` (how to read it) under the plot."""
    plt = agg_pyplot()
    w, h = image_size_px
    ix = np.clip((x_px + 0.5) / w * FIELD_CELLS, 0, FIELD_CELLS - 1).astype(int)
    iy = np.clip((y_px + 0.5) / h * FIELD_CELLS, 0, FIELD_CELLS - 1).astype(int)
    cell = iy * FIELD_CELLS + ix
    n = np.bincount(cell, minlength=FIELD_CELLS**2)
    mx = np.bincount(cell, weights=e_px[:, 0], minlength=FIELD_CELLS**2) / np.maximum(n, 1)
    my = np.bincount(cell, weights=e_px[:, 1], minlength=FIELD_CELLS**2) / np.maximum(n, 1)
    cx = (np.arange(FIELD_CELLS) + 0.5) * w / FIELD_CELLS - 0.5
    cy = (np.arange(FIELD_CELLS) + 0.5) * h / FIELD_CELLS - 0.5
    gx, gy = np.meshgrid(cx, cy)
    used = n > 0
    length = np.hypot(mx, my)
    ref = float(np.max(length[used])) if np.any(used) else 1.0
    ref = ref if ref > 0 else 1.0
    # one reference arrow of the largest mean residual spans one cell width
    scale = ref / (w / FIELD_CELLS)
    fig, ax = plt.subplots(figsize=(7, 7))
    q = ax.quiver(
        gx.ravel()[used],
        gy.ravel()[used],
        mx[used],
        my[used],
        angles="xy",
        scale_units="xy",
        scale=scale,
        color="tab:blue",
    )
    ax.quiverkey(
        q,
        0.80,
        1.02,
        ref,
        f"{ref:.3g} px mean residual (drawn {1 / scale:.3g}x enlarged)",
        labelpos="W",
        coordinates="axes",
    )
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)  # rows grow downwards, as on the detector
    ax.set_aspect("equal")
    ax.set_xlabel("x (column) [px]")
    ax.set_ylabel("y (row) [px]")
    ax.set_title(title, fontsize=10, pad=24)
    if caption:
        fig.text(0.01, 0.005, caption, fontsize=8, wrap=True, va="bottom")
        fig.tight_layout(rect=(0, 0.08, 1, 1))
    else:
        fig.tight_layout()
    save_figure(path, fig)
    plt.close(fig)


def _stages(history: list[dict]) -> list[tuple[int, int, str]]:
    """Runs of iterations fitted on the same data: (first index, last index, label). A stage begins where the number
    of stars (``n_obs``, bundle: a warm-start sample, then every frame) or the named stage (interstar methods)
    changes."""
    out: list[tuple[int, int, str]] = []
    for k, h in enumerate(history):
        if "n_obs" in h:
            label = f"{h['n_obs']} stars"
        elif "stage" in h:
            label = str(h["stage"])
        else:
            label = ""
        if out and out[-1][2] == label:
            out[-1] = (out[-1][0], k, label)
        else:
            out.append((k, k, label))
    return out


def convergence_png(path: Path, history: list[dict], title: str, converged: bool = True) -> None:
    """Residual RMS [px] (bundle; the interstar methods' cost e^T P^-1 e [px^2] for unit centroid noise) and step
    size [standard deviations of the camera] per iteration, on integer iteration ticks; each stage (a change in the
    stars fitted) shaded and labelled with its star count, and a caption saying how to read it."""
    from matplotlib.ticker import MaxNLocator

    plt = agg_pyplot()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.5, 6.8), sharex=True)
    it = [int(h["iteration"]) for h in history]
    bundle = bool(history) and "rms_px" in history[0]
    if bundle:
        a1.plot(it, [h["rms_px"] for h in history], "o-")
        a1.set_ylabel("residual RMS per star [px]")
    else:
        a1.semilogy(it, [max(h["cost"], 1e-300) for h in history], "o-")
        a1.set_ylabel("interstar cost e^T P^-1 e [px^2]")
    a1.set_title(title, fontsize=10)
    a1.grid(True, which="both", alpha=0.3)
    a2.semilogy(it, [max(h.get("step_sigmas", np.nan), 1e-12) for h in history], "s-", color="tab:orange")
    a2.set_ylabel("step [standard deviations]")
    a2.set_xlabel("iteration")
    a2.grid(True, which="both", alpha=0.3)
    a2.xaxis.set_major_locator(MaxNLocator(integer=True))
    stages = _stages(history)
    for n, (k0, k1, label) in enumerate(stages):
        x0, x1 = it[k0] - 0.4, it[k1] + 0.4
        for ax in (a1, a2):
            ax.axvspan(x0, x1, color="0.92" if n % 2 else "0.85", zorder=0, lw=0)
        a1.annotate(
            f"stage {n + 1}: {label}" if label else f"stage {n + 1}",
            xy=(0.5 * (x0 + x1), 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(0, -12),
            textcoords="offset points",
            ha="center",
            fontsize=8,
        )
    last = history[-1]["step_sigmas"] if history and "step_sigmas" in history[-1] else float("nan")
    verdict = (
        f"Converged: the last step moved the camera by {last:.2g} standard deviations."
        if converged
        else "NOT converged: the iteration limit was reached (raise --max-iter, or check the nominal)."
    )
    more = (
        " Each shaded stage fits more stars than the one before (a sample of the frames, then all of them), so a"
        " cost summed over stars jumps up there; the RMS per star should level off near the centroid noise."
        if len(stages) > 1
        else ""
    )
    fig.text(0.01, 0.005, verdict + more, fontsize=8, wrap=True, va="bottom")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_figure(path, fig)
    plt.close(fig)


def write_calibration_plots(out_dir: Path, outcome, image_size_px: tuple[int, int], nominal=None) -> tuple[Path, ...]:
    """``residual_field.png`` (after calibration), ``residual_field_before.png`` (through the ``nominal`` camera,
    when given: the pattern calibration removes) and ``convergence.png`` of a
    :class:`hostlink.calibration.run.CalibrationOutcome` into ``out_dir`` (created if missing); returns their
    paths. An unwritable folder is a one-line UserError."""
    from hostlink.calibration.model import residuals
    from hostlink.errors import UserError

    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--plot {out_dir}: cannot create ({exc.strerror})") from None
    field_png, convergence = out_dir / "residual_field.png", out_dir / "convergence.png"
    e_px = residuals(outcome.data, outcome.theta, outcome.attitudes)
    residual_field_png(
        field_png,
        outcome.data.x_px,
        outcome.data.y_px,
        e_px,
        image_size_px,
        f"{outcome.method}: mean residual per cell after calibration (RMS {outcome.after['rms_px']:.4f} px)",
        caption=AFTER_CAPTION,
    )
    written: list[Path] = [field_png]
    if nominal is not None:
        from hostlink.calibration.report import fitted_attitudes

        theta0 = nominal.model_vector()
        before_png = out_dir / "residual_field_before.png"
        e0 = residuals(outcome.data, theta0, fitted_attitudes(outcome.data, theta0))
        residual_field_png(
            before_png,
            outcome.data.x_px,
            outcome.data.y_px,
            e0,
            image_size_px,
            f"nominal camera: mean residual per cell before calibration (RMS {outcome.before['rms_px']:.4f} px)",
            caption=BEFORE_CAPTION,
        )
        written.append(before_png)
    convergence_png(
        convergence,
        outcome.history,
        f"{outcome.method}: convergence, residual and step per iteration",
        bool(outcome.converged),
    )
    written.append(convergence)
    return tuple(written)


#: What the residual-field figures say under the plot.
AFTER_CAPTION = (
    "Arrows: mean residual (measured minus predicted centroid) of the stars in each of 16 x 16 cells, each frame's "
    "attitude fitted. Arrows at the noise level in random directions: the camera model fits. Arrows turning together "
    "(a swirl, a radial pattern) that stay after calibration: a model or identification error to look into."
)
BEFORE_CAPTION = (
    "Arrows: mean residual (measured minus predicted centroid) per cell through the nominal camera, each frame's "
    "attitude fitted to it: the pattern calibration removes. Radial arrows are distortion; a uniform shift or scale, "
    "the principal point and focal length."
)
