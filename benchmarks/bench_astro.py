"""Benchmark: the onboard per-frame astrometry chain, frames per second for 20 identified stars, float32 (the sensor)
and float64 (the host reference) measured side by side in one run, with the time of each step.

Per frame (a ground sensor, seed 001 sec. 4's reference-quantity correction):
  1. apparent place of the 20 catalogue stars at the frame's time (``onboard.apparent.apparent_place_vectors``:
     space motion, light deflection, aberration, precession-nutation to TOD);
  2. the local north-up-east frame (``onboard.earth.local_frame_matrix``: sidereal time, nutation);
  3. refraction: the reference vectors lifted toward the zenith (``onboard.refraction.refract_toward_zenith``);
  4. the measured centroids through the camera model (``onboard.camera.pixels_to_unit``);
  5. the attitude (``onboard.attitude.attitude_with_rejection``: SVD + refinement, residual check).
The stars are synthetic (a 20-star field at 40 deg zenith distance through seed 004's camera, 0.05 px noise), so the
run also prints the boresight error against the truth: a benchmark of a chain that returns garbage means nothing.

    .venv/bin/python benchmarks/bench_astro.py [--frames 2000]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from onboard import attitude as att
from onboard import timescale as ts
from onboard.apparent import apparent_place_vectors, catalogue_vectors
from onboard.camera import pixels_to_unit, unit_to_pixels
from onboard.earth import local_frame_matrix
from onboard.params import params_from_dict
from onboard.refraction import refract_toward_zenith
from onboard.site import Site, Weather

N_STARS = 20
SITE = Site(39.9, 116.4, 50.0)
WEATHER = Weather(10.0, 1013.25, 0.5)
TAI_MINUS_UTC_S = 37
ARCSEC = math.pi / 648000.0
CAMERA_FILE = Path(__file__).resolve().parents[1] / "hostlink" / "data" / "seed004_camera.json"
STEPS = ("apparent place", "local frame", "refraction", "camera model", "attitude")


def make_scene(frames: int, seed: int = 1) -> dict:
    """Synthetic catalogue (Hipparcos-like epoch, proper motions, parallaxes) and per-frame centroids, in float64."""
    rng = np.random.default_rng(seed)
    cam = params_from_dict(json.loads(CAMERA_FILE.read_text()))
    theta = cam.model_vector(np.float64)
    t0 = ts.from_calendar(2026, 3, 14, 2, 10, 0)
    times = [ts.add_seconds(t0, float(k)) for k in range(frames)]
    # a boresight 40 deg from the zenith at t0, fixed in the local frame (the sensor stares while the sky turns)
    r_ig0 = local_frame_matrix(t0, SITE, 0.0, TAI_MINUS_UTC_S, np.float64)
    z = math.radians(40.0)
    bore_local = np.array([math.sin(z), math.cos(z), 0.0])
    x_local = np.cross([0.0, 1.0, 0.0], bore_local)
    x_local /= np.linalg.norm(x_local)
    r_gs = np.stack([x_local, np.cross(bore_local, x_local), bore_local])  # local -> sensor, rows x, y, boresight
    # stars in a 3.5 deg radius around the boresight (inside seed 004's 8.4 deg field)
    rho = math.radians(3.5) * np.sqrt(rng.uniform(0, 1, N_STARS))
    phi = rng.uniform(0, 2 * math.pi, N_STARS)
    b0 = np.stack([np.sin(rho) * np.cos(phi), np.sin(rho) * np.sin(phi), np.cos(rho)], axis=1)
    tod = b0 @ r_gs @ r_ig0  # TOD directions (close enough to a catalogue place: the truth is recomputed below)
    ra, dec = np.arctan2(tod[:, 1], tod[:, 0]), np.arcsin(tod[:, 2])
    pm_ra, pm_dec = rng.normal(0, 50, N_STARS), rng.normal(0, 50, N_STARS)
    plx = rng.uniform(1, 50, N_STARS)
    r0, pm = catalogue_vectors(ra, dec, pm_ra, pm_dec, np.float64)
    xy, c_true = [], []
    for t in times:
        r_ig = local_frame_matrix(t, SITE, 0.0, TAI_MINUS_UTC_S, np.float64)
        app = apparent_place_vectors(r0, pm, plx, 1991.25, ts.tt_from_utc(t, TAI_MINUS_UTC_S))
        observed = refract_toward_zenith(app @ r_ig.T, np.array([0.0, 1.0, 0.0]), WEATHER)
        x, y = unit_to_pixels(observed @ r_gs.T, theta)
        xy.append((x + rng.normal(0, 0.05, N_STARS), y + rng.normal(0, 0.05, N_STARS)))
        c_true.append(r_gs @ r_ig)  # b = C r_tod
    return {"theta": theta, "times": times, "r0": r0, "pm": pm, "plx": plx, "xy": xy, "c_true": np.array(c_true)}


def run_chain(scene: dict, dtype) -> tuple[float, dict, np.ndarray]:
    """Frames/s of the whole chain in ``dtype``, seconds per step, and the attitudes (frames, 3, 3)."""
    dt = np.dtype(dtype)
    theta = scene["theta"].astype(dt)
    r0, pm, plx = scene["r0"].astype(dt), scene["pm"].astype(dt), scene["plx"].astype(dt)
    xy = [(x.astype(dt), y.astype(dt)) for x, y in scene["xy"]]
    up = np.array([0.0, 1.0, 0.0], dtype=dt)
    threshold = dt.type(60.0 * ARCSEC)
    spent = dict.fromkeys(STEPS, 0.0)
    out = np.empty((len(xy), 3, 3))
    clock = time.perf_counter
    start = clock()
    for k, t in enumerate(scene["times"]):
        t0 = clock()
        app = apparent_place_vectors(r0, pm, plx, 1991.25, ts.tt_from_utc(t, TAI_MINUS_UTC_S))
        t1 = clock()
        r_ig = local_frame_matrix(t, SITE, 0.0, TAI_MINUS_UTC_S, dt)
        t2 = clock()
        lifted = refract_toward_zenith(app @ r_ig.T, up, WEATHER)
        t3 = clock()
        b = pixels_to_unit(xy[k][0], xy[k][1], theta)
        t4 = clock()
        c_g, _ = att.attitude_with_rejection(b, lifted, threshold)
        out[k] = c_g @ r_ig
        t5 = clock()
        for name, a, z in zip(STEPS, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5), strict=True):
            spent[name] += z - a
    return len(xy) / (clock() - start), spent, out


def boresight_rms_arcsec(c, c_true) -> float:
    a, b = c[:, 2, :], c_true[:, 2, :]
    err = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))
    return float(np.sqrt(np.mean(err**2))) / ARCSEC


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    scene = make_scene(args.frames)
    run_chain({**scene, "times": scene["times"][:20], "xy": scene["xy"][:20]}, np.float32)  # warm-up
    f32, s32, c32 = run_chain(scene, np.float32)
    f64, s64, c64 = run_chain(scene, np.float64)
    n = args.frames
    print(f"onboard astrometry chain, {N_STARS} stars/frame, {n} frames (apparent place + refraction + attitude)")
    print(f"  float32: {f32:8.0f} frames/s  ({1e3 / f32:.3f} ms/frame)")
    print(f"  float64: {f64:8.0f} frames/s  ({1e3 / f64:.3f} ms/frame)")
    print(f"  float32 / float64 speed ratio: {f32 / f64:.2f}")
    print("  per step [ms/frame]      float32   float64")
    for name in STEPS:
        print(f"    {name:<20s} {1e3 * s32[name] / n:9.3f} {1e3 * s64[name] / n:9.3f}")
    print(
        f'  boresight error vs truth (0.05 px noise): float32 {boresight_rms_arcsec(c32, scene["c_true"]):.3f}" '
        f'RMS, float64 {boresight_rms_arcsec(c64, scene["c_true"]):.3f}" RMS; '
        f'float32 - float64 {boresight_rms_arcsec(c32, c64):.4f}" RMS'
    )


if __name__ == "__main__":
    main()
