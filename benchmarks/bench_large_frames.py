"""Benchmark: how the command chain (``hostlink centroid`` -> ``identify`` -> ``calibrate``, docs/realsky.md "The
chain, command by command") scales with the frame's size and star count (issue 30: a user's DSLR-sized wide-field
JPEG, a 16-bit FITS of a large sensor). Renders large frames with the project's renderer (``hostlink.sky.simulate``
then ``hostlink.sky.render``, the field effects of the 50-deg stress set: ``benchmarks/bench_widefield.py``), runs
each stage as a user would, in a fresh process per stage, and reports per stage the peak resident memory and CPU time
(user + system) of that process (GNU time, ``/usr/bin/time``), per Mpx and per row; optionally the same for the
granasat frames (STARTRACKER_REALSKY_ROOT, docs/realsky.md "The sets") as the small-frame reference, and
(``--copies N``) ``calibrate`` on a kind's identified frame copied into N frames (memory against frames). A stage
that fails is reported with its exit code and the chain of that kind stops.

Kinds (``--kind``, repeatable):

- ``jpeg24``: 6000 x 4000 px (24 Mpx), 55 deg across, a "mustache" lens (k1 bends the corner in by 20 % of its
  radius, k2 back out by 8 %) the nominal does not know, the nominal's focal length 4 % long, coma, vignetting and a
  sky gradient, to Hp 11 (Hipparcos's faint end); written as a colour camera's 8-bit JPEG (Bayer mosaic, quality 85);
- ``fits16``: 4096 x 4096 px (16.8 Mpx), 40 deg across, 3 % barrel at the corner, to Hp 11, 16-bit FITS.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_large_frames.py [--kind jpeg24] [--kind fits16] [--frames N]
        [--granasat] [--copies N] [--out DIR] [--json OUT]

Run on demand (about two minutes with --granasat --copies 10 on one core), never in the tests.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PITCH_UM = 4.3
SEED = 5
WHITE_ADU = 900.0
JPEG_QUALITY = 85
#: GNU time: the child's peak resident memory and CPU time (Debian's package ``time``).
GNU_TIME = "/usr/bin/time"


@dataclass(frozen=True)
class Kind:
    name: str
    width: int
    height: int
    fov_deg: float
    k1_corner: float
    k2_corner: float
    maglim: float
    jpeg: bool


KINDS = {
    "jpeg24": Kind("jpeg24", 6000, 4000, 55.0, -0.20, 0.08, 11.0, True),
    "fits16": Kind("fits16", 4096, 4096, 40.0, -0.03, 0.0, 11.0, False),
}


def true_camera(kind: Kind):
    from onboard.params import CameraParams, Distortion

    focal_px = 0.5 * kind.width / math.tan(math.radians(0.5 * kind.fov_deg))
    half_diagonal = 0.5 * math.hypot(kind.width, kind.height)
    return CameraParams(
        focal_length_mm=focal_px * PITCH_UM * 1e-3,
        pixel_pitch_um=PITCH_UM,
        principal_point_px=(0.5 * (kind.width - 1) + 16.0, 0.5 * (kind.height - 1) - 12.0),
        image_size_px=(kind.width, kind.height),
        distortion=Distortion(k1=kind.k1_corner / half_diagonal**2, k2=kind.k2_corner / half_diagonal**4),
    )


def nominal_json(kind: Kind) -> dict:
    camera = true_camera(kind)
    return {
        "focal_length_mm": camera.focal_length_mm * 1.04,
        "pixel_pitch_um": PITCH_UM,
        "principal_point_px": [0.5 * (kind.width - 1), 0.5 * (kind.height - 1)],
        "image_size_px": [kind.width, kind.height],
    }


def render_config(kind: Kind, frame: int):
    from hostlink.sky.render import FieldEffects, RenderConfig

    effects = (
        FieldEffects(
            psf_corner_factor=2.0, coma_fraction=0.3, coma_corner_px=2.0, vignetting_corner=0.4, gradient_e=150.0
        )
        if kind.jpeg
        else FieldEffects()
    )
    return RenderConfig(
        psf_sigma_px=1.3,
        zero_point_e=1.5e6 if kind.jpeg else 4.0e7,
        background_e=300.0,
        read_noise_e=6.0,
        bits=12 if kind.jpeg else 16,
        hot_pixels=200,
        seed=SEED + frame,
        effects=effects,
    )


def render(kind: Kind, frames: int, out_dir: Path, log=print) -> list[Path]:
    """Render ``frames`` frames of ``kind`` into ``out_dir``; returns their paths."""
    from hostlink.sky.render import bayer_jpeg_rgb, expected_electrons
    from hostlink.sky.simulate import SimConfig, simulate

    sim = simulate(
        SimConfig(
            camera=true_camera(kind),
            frames=frames,
            noise_px=0.0,
            min_stars=8,
            max_stars=1_000_000,
            maglim=kind.maglim,
            seed=SEED,
        )
    )
    s = sim.session
    paths = []
    for k in range(frames):
        config = render_config(kind, k)
        rows = np.flatnonzero((s.frame == k) & (s.star_id != 0))
        flux = config.zero_point_e * 10.0 ** (-0.4 * s.mag[rows])
        mu = expected_electrons(s.x_px[rows], s.y_px[rows], flux, (kind.width, kind.height), config)
        rng = np.random.default_rng(config.seed)
        electrons = rng.poisson(mu).astype(np.float32)
        del mu
        hot = rng.integers(0, [kind.width, kind.height], (config.hot_pixels, 2))
        electrons[hot[:, 1], hot[:, 0]] += config.hot_pixel_e
        electrons += rng.normal(0.0, config.read_noise_e, electrons.shape).astype(np.float32)
        counts = np.clip(np.round(config.bias_adu + electrons / config.gain_e_per_adu), 0, config.saturation_adu)
        del electrons
        if kind.jpeg:
            from PIL import Image

            path = out_dir / f"{kind.name}_{k:02d}.jpg"
            Image.fromarray(bayer_jpeg_rgb(counts, config, WHITE_ADU), "RGB").save(path, quality=JPEG_QUALITY)
        else:
            from astropy.io import fits

            path = out_dir / f"{kind.name}_{k:02d}.fits"
            fits.PrimaryHDU(counts.astype(np.uint16)).writeto(path, overwrite=True)
        paths.append(path)
        log(f"{path.name}: {rows.size} catalogue stars in the frame (Hp <= {kind.maglim})")
    return paths


def run_stage(args: list[str], log=print) -> dict:
    """Run ``hostlink ARGS`` in a fresh process: its peak resident memory [MB] and CPU time [s], measured by GNU time
    (``/usr/bin/time``) around the child, so the parent's own memory (a render) is not counted: a child's
    ``ru_maxrss`` from ``os.wait4`` keeps the forked parent's high-water mark on Linux."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as timing:
        command = [
            GNU_TIME, "-f", "%M %U %S", "-o", timing.name,
            sys.executable, "-c", "import sys; from hostlink.cli import main; sys.exit(main())", *args,
        ]  # fmt: skip
        process = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        maxrss_kb, user_s, system_s = timing.read().split()[-3:]
    return {
        "exit_code": process.returncode,
        "peak_rss_mb": float(maxrss_kb) / 1024.0,
        "cpu_s": float(user_s) + float(system_s),
        "output_tail": process.stdout.strip().splitlines()[-4:],
    }


def _rows(csv_path: Path) -> int:
    with open(csv_path) as handle:
        return sum(1 for line in handle if line.strip() and not line.startswith("#")) - 1


def _identified(csv_path: Path) -> int:
    import csv

    with open(csv_path, newline="") as handle:
        return sum(1 for row in csv.DictReader(handle) if row["star_id"] not in ("", "0"))


def calibrate_copies(name: str, work: Path, copies: int, log=print) -> dict:
    """``calibrate`` on the identified stars of frame 0 of ``name`` copied into ``copies`` frames: how its memory and
    time grow with the frames of a session of large frames."""
    import csv

    with open(work / f"{name}_id.csv", newline="") as handle:
        rows = [row for row in csv.DictReader(handle) if row["star_id"] not in ("", "0") and row["frame"] == "0"]
    path = work / f"{name}_x{copies}_id.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        for k in range(copies):
            writer.writerows({**row, "frame": str(k)} for row in rows)
    args = ["calibrate", str(path), "--nominal", str(work / f"{name}_nominal.json"), "--out", str(work / "x.json")]
    figures = run_stage(args, log)
    figures["stars_per_frame"] = len(rows)
    log(
        f"{name} calibrate x{copies} ({len(rows)} stars a frame): peak {figures['peak_rss_mb']:.0f} MB, CPU "
        f"{figures['cpu_s']:.1f} s, exit {figures['exit_code']}"
    )
    return figures


def run_chain(
    name: str, images: list[Path], nominal: dict, work: Path, pixels: int, extra_centroid=(), log=print
) -> dict:
    """The three stages on ``images``; per stage the figures of :func:`run_stage` with per-Mpx and per-star ones."""
    nominal_path = work / f"{name}_nominal.json"
    nominal_path.write_text(json.dumps(nominal))
    cents, ident, report = work / f"{name}.csv", work / f"{name}_id.csv", work / f"{name}_id.json"
    stages = {
        "centroid": ["centroid", *map(str, images), "--time-unknown", *extra_centroid, "--out", str(cents)],
        "identify": [
            "identify",
            str(cents),
            "--nominal",
            str(nominal_path),
            "--out",
            str(ident),
            "--report",
            str(report),
        ],
        "calibrate": ["calibrate", str(ident), "--nominal", str(nominal_path), "--out", str(work / f"{name}_cal.json")],
    }
    result = {"images": len(images), "mpx": pixels / 1e6, "stages": {}}
    for stage, args in stages.items():
        figures = run_stage(args, log)
        result["stages"][stage] = figures
        if figures["exit_code"] != 0:  # a failed stage is reported (its memory and time too), the chain stops
            log(f"{name} {stage}: failed (exit {figures['exit_code']}): {' | '.join(figures['output_tail'])}")
            break
        if stage == "centroid":
            result["rows"] = _rows(cents)
        if stage == "identify":
            result["identified"] = _identified(ident)
        per = result["rows"] if stage != "calibrate" else result["identified"]
        figures["cpu_s_per_mpx"] = figures["cpu_s"] / (pixels / 1e6)
        figures["cpu_ms_per_row"] = 1e3 * figures["cpu_s"] / max(per, 1)
        log(
            f"{name} {stage}: peak {figures['peak_rss_mb']:.0f} MB, CPU {figures['cpu_s']:.1f} s "
            f"({figures['cpu_s_per_mpx']:.2f} s/Mpx, {figures['cpu_ms_per_row']:.2f} ms/row); "
            + " | ".join(figures["output_tail"][-2:])
        )
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", action="append", choices=sorted(KINDS), help="default: both")
    parser.add_argument("--frames", type=int, default=1, help="frames per kind (default 1)")
    parser.add_argument("--granasat", action="store_true", help="the granasat frames too (STARTRACKER_REALSKY_ROOT)")
    parser.add_argument("--out", type=Path, help="keep the frames and outputs here (default: a temporary folder)")
    parser.add_argument(
        "--copies", type=int, default=0, help="also calibrate each kind's identified frame copied into N frames"
    )
    parser.add_argument("--json", type=Path, metavar="OUT", help="write the figures as JSON")
    args = parser.parse_args(argv)
    figures = {}
    with tempfile.TemporaryDirectory() as scratch:
        work = args.out or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        if args.granasat:
            root = os.environ.get("STARTRACKER_REALSKY_ROOT")
            if not root:
                raise SystemExit("--granasat needs STARTRACKER_REALSKY_ROOT (docs/realsky.md)")
            images = sorted((Path(root) / "granasat").glob("*.jpg"))
            nominal = {
                "focal_length_mm": 12.3565845,
                "pixel_pitch_um": 4.65,
                "principal_point_px": [666.0, 440.0],
                "image_size_px": [1280, 960],
            }
            figures["granasat"] = run_chain("granasat", images, nominal, work, 1280 * 960 * len(images))
        for name in args.kind or sorted(KINDS):
            kind = KINDS[name]
            images = render(kind, args.frames, work)
            figures[name] = run_chain(name, images, nominal_json(kind), work, kind.width * kind.height * len(images))
            if args.copies and "identified" in figures[name]:
                figures[name][f"calibrate_x{args.copies}"] = calibrate_copies(name, work, args.copies)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
