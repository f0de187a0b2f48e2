"""Figures of a calibration (matplotlib, Agg backend): the residual vector field and the convergence history."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostlink.files.atomic import save_figure

#: Cells per detector side of the binned residual field (each arrow is the mean residual of one cell).
FIELD_CELLS = 16


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def residual_field_png(
    path: Path, x_px: np.ndarray, y_px: np.ndarray, e_px: np.ndarray, image_size_px: tuple[int, int], title: str
) -> None:
    """Mean residual per cell of a 16 x 16 grid over the detector, as arrows; the scale is stated in the legend."""
    plt = _pyplot()
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
    fig.tight_layout()
    save_figure(path, fig)
    plt.close(fig)


def convergence_png(path: Path, history: list[dict], title: str) -> None:
    """Cost (log scale) and step size per iteration."""
    plt = _pyplot()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    it = [h["iteration"] for h in history]
    a1.semilogy(it, [max(h["cost"], 1e-300) for h in history], "o-")
    a1.set_ylabel("cost (robust, px^2 or whitened)")
    a1.set_title(title, fontsize=10)
    a1.grid(True, which="both", alpha=0.3)
    a2.semilogy(it, [max(h.get("step_sigmas", np.nan), 1e-12) for h in history], "s-", color="tab:orange")
    a2.set_ylabel("step [standard deviations]")
    a2.set_xlabel("iteration")
    a2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(path, fig)
    plt.close(fig)


def write_calibration_plots(out_dir: Path, outcome, image_size_px: tuple[int, int]) -> tuple[Path, Path]:
    """``residual_field.png`` and ``convergence.png`` of a :class:`hostlink.calibration.run.CalibrationOutcome`
    into ``out_dir`` (created if missing); returns their paths. An unwritable folder is a one-line UserError."""
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
    )
    convergence_png(convergence, outcome.history, f"{outcome.method}: convergence")
    return field_png, convergence
