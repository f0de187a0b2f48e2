"""Benchmark: a realistic wide-field stress set (issue 30) rendered by the project, run through the command-line chain
as a user would (``hostlink centroid --time-unknown``, ``identify --nominal``, ``calibrate``), and through tetra3rs
from the same images, side by side; the figures of docs/realsky.md ("Wider and narrower fields").

The set: FRAMES frames of a 50 deg (horizontal) camera, 1600 x 1200 px, at random pointings (the real Hipparcos
sky, ``hostlink.sky.simulate``), through a lens whose distortion the nominal does not know: radial terms of opposite
sign (a "mustache": k1 barrel, k2 back outward; 12 % of the radius at the corner) and a principal point 20 px off the
centre; the nominal's focal length is 4 % long and has no distortion. Rendered (``hostlink.sky.render`` with its
field effects) with a PSF twice as wide at the corners as at the centre and comatic there, 40 % vignetting at the
corner, a sky gradient, then as a colour camera's JPEG (Bayer mosaic interpolated, quality 85). Frames also get, by
a fixed draw: one or two planets (points brighter than any star, not in the catalogue), a satellite trail, a
horizon (the bottom quarter of the frame a bright light-polluted glow, or black trees with no stars), or clouds (a
smooth random transmission that hides stars and adds glow). The truth of each centroid is the true star within
:data:`MATCH_PX` (a planet, trail or noise detection has none: any name on it is wrong).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_widefield.py [--frames N] [--out DIR] [--json OUT] [--no-solver]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

FRAMES = 24
WIDTH, HEIGHT = 1600, 1200
FOV_DEG = 50.0
PITCH_UM = 4.65
#: The true lens's radial distortion as fractions of the radius at the corner: k1 r^2 gives -20 %, k2 r^4 +8 %.
K1_CORNER, K2_CORNER = -0.20, 0.08
PRINCIPAL_OFFSET_PX = (16.0, -12.0)
NOMINAL_FOCAL_ERROR = 0.04
SIM_MAGLIM = 7.0
#: A centroid is the image of a true star when this close to it [px] (coma moves a corner star's light centroid by
#: up to ~0.6 px; stars of the set closer than this to each other are rare at Hp 7 over 50 deg).
MATCH_PX = 1.5
#: A name is right when the named star is the true star nearest the centroid and within this distance [px] (a
#: saturated or comatic bright star's centroid lies up to ~2.5 px from its chief ray), or lies within BLEND_PX of it
#: together with the nearest (an unresolved pair: either name is the pair's).
NAME_PX = 3.0
BLEND_PX = 1.0
SEED = 11


def true_camera():
    from onboard.params import CameraParams, Distortion

    focal_px = 0.5 * WIDTH / math.tan(math.radians(0.5 * FOV_DEG))
    half_diagonal = 0.5 * math.hypot(WIDTH, HEIGHT)
    return CameraParams(
        focal_length_mm=focal_px * PITCH_UM * 1e-3,
        pixel_pitch_um=PITCH_UM,
        principal_point_px=(0.5 * (WIDTH - 1) + PRINCIPAL_OFFSET_PX[0], 0.5 * (HEIGHT - 1) + PRINCIPAL_OFFSET_PX[1]),
        image_size_px=(WIDTH, HEIGHT),
        distortion=Distortion(k1=K1_CORNER / half_diagonal**2, k2=K2_CORNER / half_diagonal**4),
    )


def nominal_camera(camera):
    from onboard.params import Distortion

    return replace(
        camera,
        focal_length_mm=camera.focal_length_mm * (1.0 + NOMINAL_FOCAL_ERROR),
        principal_point_px=(0.5 * (WIDTH - 1), 0.5 * (HEIGHT - 1)),
        distortion=Distortion(),
    )


def render_config():
    from hostlink.sky.render import FieldEffects, RenderConfig

    return RenderConfig(
        psf_sigma_px=1.3,
        zero_point_e=1.5e6,
        background_e=300.0,
        read_noise_e=6.0,
        hot_pixels=30,
        seed=SEED,
        effects=FieldEffects(
            psf_corner_factor=2.0, coma_fraction=0.3, coma_corner_px=2.0, vignetting_corner=0.4, gradient_e=150.0
        ),
    )


#: The JPEG's white level [ADU above bias]: the camera's stretch (the faint stars then span a few 8-bit steps).
WHITE_ADU = 900.0
JPEG_QUALITY = 85


def _extras(k: int, rng: np.random.Generator) -> dict:
    """Frame k's additions, a fixed draw: planets, a trail, a horizon (bright or trees) or clouds."""
    return {
        "planets": int(rng.integers(1, 3)) if k % 3 == 0 else 0,
        "trail": k % 4 == 1,
        "horizon": ("glow" if k % 2 else "trees") if k % 8 in (2, 5) else None,
        "clouds": k % 8 == 7,
    }


def render_set(out_dir: Path, frames: int = FRAMES, log=print) -> list[dict]:
    """Render the set into ``out_dir`` (frame_NN.jpg) and return per frame its truth: rows of (x, y, hip) of the
    stars left visible, and what was added."""
    from PIL import Image

    from hostlink.sky.render import bayer_jpeg_rgb
    from hostlink.sky.simulate import SimConfig, simulate

    config = render_config()
    sim = simulate(
        SimConfig(
            camera=true_camera(),
            frames=frames,
            noise_px=0.0,
            min_stars=8,
            max_stars=100_000,
            maglim=SIM_MAGLIM,
            seed=SEED,
        )
    )
    rng = np.random.default_rng(SEED)  # one stream for every frame, drawn in frame order
    truths = []
    for k in range(frames):
        truth, counts = _render_frame(sim.session, k, config, rng)
        path = out_dir / f"frame_{k:02d}.jpg"
        Image.fromarray(bayer_jpeg_rgb(counts, config, WHITE_ADU), "RGB").save(path, quality=JPEG_QUALITY)
        truths.append({"image": path.name, **truth})
        log(
            f"{path.name}: {int(np.count_nonzero(truth['visible']))} stars visible of {truth['x'].size}, planets "
            f"{truth['planets']}, trail {truth['trail']}, horizon {truth['horizon']}, clouds {truth['clouds']}"
        )
    return truths


def _render_frame(s, k: int, config, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """Frame ``k`` of the simulated session ``s``: its truth (the stars, which of them stay visible, the planets and
    the additions of :func:`_extras`) and its detector counts [ADU]."""
    from hostlink.sky.render import expected_electrons

    rows = np.flatnonzero((s.frame == k) & (s.star_id != 0))
    x, y, hip, mag = s.x_px[rows], s.y_px[rows], s.star_id[rows], s.mag[rows]
    flux = config.zero_point_e * 10.0 ** (-0.4 * mag)
    extra = _extras(k, rng)
    px, py, pflux = _planets(extra["planets"], config, rng)
    mu = expected_electrons(
        np.concatenate([x, px]), np.concatenate([y, py]), np.concatenate([flux, pflux]), (WIDTH, HEIGHT), config
    )
    visible = np.ones(x.size, dtype=bool)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    if extra["trail"]:
        mu += _trail_e(xx, yy, rng)
    if extra["clouds"]:
        mu, seen = _through_clouds(mu, x, y, config, rng)
        visible &= seen
    if extra["horizon"]:
        visible &= _below_horizon(mu, x, y, extra["horizon"], config, xx, yy)
    truth = {"x": x, "y": y, "hip": hip, "visible": visible, "planets_xy": np.stack([px, py], axis=1), **extra}
    return truth, _exposed_counts(mu, config, rng)


def _planets(n: int, config, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` uncatalogued points brighter than any star (Venus to Saturn: Hp -4 to 0.5): x, y [px] and flux [e-]."""
    px = rng.uniform(50, WIDTH - 50, n)
    py = rng.uniform(50, HEIGHT - 50, n)
    pflux = config.zero_point_e * 10.0 ** (-0.4 * rng.uniform(-4.0, 0.5, n))
    return px, py, pflux


def _trail_e(xx: np.ndarray, yy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A satellite: a straight streak across the frame [e- per pixel]."""
    x0, y0, angle = rng.uniform(0, WIDTH), rng.uniform(0, HEIGHT), rng.uniform(0, math.pi)
    dist = np.abs(-(xx - x0) * math.sin(angle) + (yy - y0) * math.cos(angle))
    return 400.0 * np.exp(-0.5 * (dist / 1.5) ** 2)


def _through_clouds(mu, x, y, config, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``mu`` [e-] through a smooth random transmission 0.05-1, with glow where thick, and which stars stay seen
    (transmission above 0.3 at their pixel)."""
    from scipy.ndimage import gaussian_filter

    field = gaussian_filter(rng.normal(size=(HEIGHT, WIDTH)), 80.0)
    field = (field - field.min()) / (field.max() - field.min())
    transmission = np.clip(1.6 * field - 0.3, 0.05, 1.0)
    mu = config.background_e + (mu - config.background_e) * transmission + 400.0 * (1.0 - transmission)
    t_star = transmission[
        np.clip(np.round(y).astype(int), 0, HEIGHT - 1), np.clip(np.round(x).astype(int), 0, WIDTH - 1)
    ]
    return mu, t_star > 0.3


def _below_horizon(mu, x, y, kind: str, config, xx, yy) -> np.ndarray:
    """Fill ``mu`` [e-] below a wavy horizon with a glow (``kind`` "glow") or dark trees, in place; which stars stay
    above it (by 3 px)."""
    horizon_row = int(0.75 * HEIGHT) + (20.0 * np.sin(xx[0] / 150.0)).astype(int)
    below = yy >= horizon_row[None, :]
    level = 1200.0 if kind == "glow" else 0.3 * config.background_e
    mu[below] = level * (1.0 + 0.3 * (yy[below] - 0.75 * HEIGHT) / HEIGHT)
    col = np.clip(np.round(x).astype(int), 0, WIDTH - 1)
    return y < horizon_row[col] - 3


def _exposed_counts(mu: np.ndarray, config, rng: np.random.Generator) -> np.ndarray:
    """The detector's counts [ADU] for the expected electrons ``mu``: shot noise, hot pixels, read noise, bias,
    gain and saturation."""
    electrons = rng.poisson(mu).astype(np.float64)
    hot = rng.integers(0, [WIDTH, HEIGHT], size=(config.hot_pixels, 2))
    electrons[hot[:, 1], hot[:, 0]] += config.hot_pixel_e
    electrons += rng.normal(0.0, config.read_noise_e, electrons.shape)
    return np.clip(np.round(config.bias_adu + electrons / config.gain_e_per_adu), 0, config.saturation_adu)


def _hostlink(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", "import sys; from hostlink.cli import main; sys.exit(main())", *args]
    return subprocess.run(cmd, capture_output=True, text=True, check=False)


def run_chain(work: Path, nominal_path: Path, log=print) -> dict:
    """The command-line chain on the set's images; returns the paths and the process times."""
    images = sorted(str(p) for p in work.glob("frame_*.jpg"))
    times = {}
    steps = {
        "centroid": ["centroid", *images, "--time-unknown", "--out", str(work / "c.csv"), "--quiet"],
        "identify": [
            "identify",
            str(work / "c.csv"),
            "--nominal",
            str(nominal_path),
            "--out",
            str(work / "id.csv"),
            "--report",
            str(work / "id.json"),
        ],
        "calibrate": [
            "calibrate",
            str(work / "id.csv"),
            "--nominal",
            str(nominal_path),
            "--out",
            str(work / "cal.json"),
            "--rejected",
            str(work / "rejected.csv"),
            "--keep-failed",
            "--quiet",
        ],
    }
    for name, args in steps.items():
        t0 = time.perf_counter()
        done = _hostlink(*args)
        times[name] = time.perf_counter() - t0
        tail = (done.stdout + done.stderr).strip().splitlines()
        log(f"hostlink {name}: exit {done.returncode} ({times[name]:.1f} s)" + "".join(f"\n  {t}" for t in tail[-6:]))
    return times


def _truth_of(x: np.ndarray, y: np.ndarray, sid: np.ndarray, truth: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per centroid: the visible true star within MATCH_PX (0 when none), and whether its name (when named) is wrong
    (:data:`NAME_PX`, :data:`BLEND_PX`)."""
    tx, ty, hip = truth["x"], truth["y"], truth["hip"]
    if tx.size == 0:
        return np.zeros(x.size, np.int64), sid != 0
    d = np.hypot(x[:, None] - tx[None], y[:, None] - ty[None])
    nearest = np.argmin(d, axis=1)
    near_d = d[np.arange(x.size), nearest]
    true_id = np.where((near_d < MATCH_PX) & truth["visible"][nearest], hip[nearest], 0)
    right = np.zeros(x.size, dtype=bool)
    for i in np.flatnonzero(sid != 0):
        j = np.flatnonzero(hip == sid[i])
        if j.size == 0:
            continue
        dj = float(d[i, j[0]])
        right[i] = (hip[nearest[i]] == sid[i] and dj <= NAME_PX) or (dj <= BLEND_PX and near_d[i] <= BLEND_PX)
    return true_id, (sid != 0) & ~right


def score(work: Path, truths: list[dict]) -> dict:
    """Ours against the truth: frames identified, stars, wrong names, calibrate's rejections and residual."""
    from hostlink.files.session import read_session

    session = read_session(work / "id.csv")
    report = json.loads((work / "id.json").read_text())
    cal = json.loads((work / "cal.json").read_text())
    starts = session.frame_starts
    images = session.extra.get("image")
    named_total = wrong_total = detectable_total = found_total = 0
    per_frame = []
    for k, truth in enumerate(truths):
        a, b = int(starts[k]), int(starts[k + 1])
        if images is not None:
            assert Path(str(images[a])).name == truth["image"]
        x, y, sid = session.x_px[a:b], session.y_px[a:b], session.star_id[a:b]
        true_id, wrong = _truth_of(x, y, sid, truth)
        named = sid != 0
        named_total += int(np.count_nonzero(named))
        wrong_total += int(np.count_nonzero(wrong))
        detectable_total += int(np.count_nonzero(true_id != 0))
        found_total += int(np.count_nonzero(named & (sid == true_id)))
        per_frame.append(
            {
                "image": truth["image"],
                "named": int(np.count_nonzero(named)),
                "wrong": int(np.count_nonzero(wrong)),
                "detected_true": int(np.count_nonzero(true_id != 0)),
            }
        )
    after = cal.get("residuals", {}).get("after", cal.get("after", {}))
    return {
        "frames_identified": report["frames_identified"],
        "frames": len(truths),
        "stars_named": named_total,
        "wrong_names": wrong_total,
        "detected_true_stars": detectable_total,
        "true_stars_named": found_total,
        "calibration": {k: cal.get(k) for k in ("status", "n_rejected", "method")}
        | {"after": after, "noise_model": cal.get("noise_model")}
        | {k: cal.get(k) for k in ("focal_length_mm", "principal_point_px", "sigma")},
        "per_frame": per_frame,
        "rounds": report.get("rounds"),
        "per_frame_status": [f["status"] for f in report["per_frame"]],
    }


def solver_side(work: Path, truths: list[dict], nominal) -> dict:
    """tetra3rs from the same images: frames solved, its wrong names against the truth, its own calibration."""
    from hostlink.images import solver_adapter
    from hostlink.images.read import read_image
    from hostlink.sky.catalogue import load_catalogue

    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, WIDTH)
    database = solver_adapter.pattern_database(load_catalogue(), fov)
    solved = named = wrong = 0
    frames = []
    for truth in truths:
        pixels = read_image(work / truth["image"]).pixels
        e = solver_adapter.engine_solve_image(database, pixels, fov)
        frames.append((e.x_px - 0.5 * (WIDTH - 1), e.y_px - 0.5 * (HEIGHT - 1), e.brightness))
        if not e.solved:
            continue
        solved += 1
        _, bad = _truth_of(e.x_px[e.rows], e.y_px[e.rows], e.hip, truth)
        named += int(e.rows.size)
        wrong += int(np.count_nonzero(bad))
    cal = solver_adapter.engine_calibration(database, frames, (WIDTH, HEIGHT), fov)
    return {
        "frames_solved": solved,
        "stars_named": named,
        "wrong_names": wrong,
        "calibrated_rmse_px": None if cal is None else cal.rmse_px,
        "calibration_outliers": None if cal is None else cal.n_outliers,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=FRAMES)
    parser.add_argument("--out", help="folder for the images and session files (default: a temporary one)")
    parser.add_argument("--json", metavar="OUT", help="write the figures as JSON")
    parser.add_argument("--no-solver", action="store_true", help="skip tetra3rs")
    parser.add_argument("--reuse", action="store_true", help="use the images already in --out")
    args = parser.parse_args()
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="widefield_"))
    work.mkdir(parents=True, exist_ok=True)
    from hostlink.files.params import params_to_dict

    truth_file = work / "truth.npz"
    if args.reuse and truth_file.exists():
        truths = list(np.load(truth_file, allow_pickle=True)["truths"])
    else:
        truths = render_set(work, args.frames)
        np.savez(truth_file, truths=np.array(truths, dtype=object))
    nominal = nominal_camera(true_camera())
    nominal_path = work / "nominal.json"
    nominal_path.write_text(json.dumps(params_to_dict(nominal)))
    (work / "true.json").write_text(json.dumps(params_to_dict(true_camera())))  # for bench_noise_model.py --truth
    os.environ.setdefault("PYTHONPATH", str(Path(__file__).resolve().parents[1]))
    times = run_chain(work, nominal_path)
    result = {"ours": score(work, truths), "time_s": times}
    if not args.no_solver:
        result["solver"] = solver_side(work, truths, nominal)
    ours = result["ours"]
    print(
        f"ours: {ours['frames_identified']} of {ours['frames']} frames, {ours['stars_named']} stars named, "
        f"{ours['wrong_names']} wrong, {ours['true_stars_named']} of {ours['detected_true_stars']} detected true "
        f"stars; "
        f"calibration {ours['calibration']}"
    )
    print("statuses:", ours["per_frame_status"])
    if "solver" in result:
        print("solver:", result["solver"])
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str))


if __name__ == "__main__":
    main()
