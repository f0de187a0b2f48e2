"""Benchmark: the centroid stage alone (images -> centroids, ``centroid_images`` as benchmarks/bench_realsky.py's
``_run_ours`` calls it, time unknown) on a real image set (granasat by default, or openstartracker), CPU seconds of
this process (time.process_time: the machine may be shared), for the tree it runs in (issue 30). Run it alternately
on two trees to compare them side by side:

    PYTHONPATH=/path/to/baseline .venv/bin/python benchmarks/bench_centroid_speed.py --repeat 3 --rows base.npz
    PYTHONPATH=. .venv/bin/python benchmarks/bench_centroid_speed.py --repeat 3 --rows new.npz
    .venv/bin/python benchmarks/bench_centroid_speed.py --compare base.npz new.npz

``--rows`` writes every frame's detections at full precision (x, y, sigma_px, flux, saturated, blended, the
candidates' snr; per frame the report's stars kept, PSF sigma and median noise) and the session's text columns for
``--compare``, which prints the counts and the largest differences; ``--identify`` identifies the detected stars
once. STARTRACKER_REALSKY_ROOT names the folder of the image sets (docs/realsky.md)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

_COLUMNS = ("sigma_px", "flux_adu", "saturated", "blended", "snr", "report")


def _paths(set_name: str) -> list[Path]:
    from bench_realsky import SETS

    root = os.environ.get("STARTRACKER_REALSKY_ROOT")
    if root is None:
        sys.exit("bench_centroid_speed: set STARTRACKER_REALSKY_ROOT to the folder of the image sets")
    pattern = SETS[set_name].pattern
    paths = sorted((Path(root) / set_name).glob(pattern))
    if not paths:
        sys.exit(f"bench_centroid_speed: no {pattern} under {Path(root) / set_name}")
    return paths


def _options(set_name: str):
    """The set's centroiding as benchmarks/bench_realsky.py's ``_run_ours`` (openstartracker: the median of its
    frames subtracted, 3 sigma)."""
    from bench_realsky import SETS

    from hostlink.images.centroid import CentroidOptions

    image_set = SETS[set_name]
    return CentroidOptions(threshold_sigma=image_set.threshold_sigma, median_of_inputs=image_set.median_of_inputs)


def _rows(paths: list[Path], options) -> dict[str, np.ndarray]:
    """Every frame's detections at full precision (``centroid_pixels`` of each image, as ``centroid_images`` calls
    it), stars then candidates, and per frame its report's figures."""
    from hostlink.images.centroid import centroid_pixels
    from hostlink.images.centroid.session import _background_frame
    from hostlink.images.read import read_image

    background = _background_frame(paths, options)

    parts: dict[str, list[np.ndarray]] = {}
    for k, path in enumerate(paths):
        image = read_image(path)
        det = centroid_pixels(image.pixels, options, background, image.saturation_adu)
        c = det.candidates
        rows = {
            "frame": np.full(det.x_px.size + (c.x_px.size if c else 0), k),
            "x": np.concatenate([det.x_px, c.x_px if c else []]),
            "y": np.concatenate([det.y_px, c.y_px if c else []]),
            "sigma_px": np.concatenate([det.sigma_px, c.sigma_px if c else []]),
            "flux_adu": np.concatenate([det.flux_adu, c.flux_adu if c else []]),
            "saturated": np.concatenate([det.saturated, np.zeros(c.x_px.size if c else 0)]),
            "blended": np.concatenate([det.blended, np.zeros(c.x_px.size if c else 0)]),
            "snr": np.concatenate([np.full(det.x_px.size, np.nan), c.snr if c else []]),
        }
        report = det.report
        rows["report"] = np.array([[report.kept, report.psf_sigma_px, report.background_rms_adu]])
        for name, values in rows.items():
            parts.setdefault(name, []).append(np.asarray(values, dtype=np.float64))
    return {name: np.concatenate(values) for name, values in parts.items()}


def _time(paths: list[Path], options, repeat: int):
    from hostlink.images.centroid import TimeOptions, centroid_images

    seconds = []
    for _ in range(repeat):
        t0 = time.process_time()
        result = centroid_images(paths, options, TimeOptions(time_unknown=True))
        seconds.append(time.process_time() - t0)
    return seconds, result


def _identify_once(result, set_name: str) -> None:
    """``identify_session`` of the detected stars (the candidates left out), as benchmarks/bench_realsky.py's
    ``_run_ours`` identifies once: the stars identified and the frames with an attitude."""
    from bench_realsky import SETS

    from hostlink.files.params import params_from_dict
    from hostlink.images.guided import candidate_rows
    from hostlink.images.identify import identify_session

    detected = result.session.select(~candidate_rows(result.session))
    once = identify_session(detected, params_from_dict(SETS[set_name].nominal))
    print(f"identified once: {once.n_identified} of {detected.x_px.size} detected stars")


def _compare(a_path: str, b_path: str) -> None:
    a, b = np.load(a_path), np.load(b_path)
    print(f"rows: {a['x'].size} / {b['x'].size}")
    if a["x"].size != b["x"].size or not np.array_equal(a["frame"], b["frame"]):
        print("different rows per frame:", np.bincount(a["frame"].astype(int)), np.bincount(b["frame"].astype(int)))
        return
    texts = sorted(name for name in a.files if name.startswith("text_"))
    same = [name[5:] for name in texts if name in b.files and np.array_equal(a[name], b[name])]
    print(f"session columns written the same: {len(same)} of {len(texts)} ({', '.join(same)})")
    for name in ("x", "y", *_COLUMNS):
        if name not in a.files or name not in b.files:
            continue
        u, v = a[name], b[name]
        same_nan = np.array_equal(np.isnan(u), np.isnan(v))
        finite = np.isfinite(u) & np.isfinite(v)
        diff = float(np.max(np.abs(u[finite] - v[finite]))) if finite.any() else 0.0
        print(f"{name:10s} max |diff| {diff:.3g}  NaN in the same rows: {same_nan}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--set", default="granasat", choices=("granasat", "openstartracker"))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--rows", help="write the session's rows (.npz) for --compare")
    parser.add_argument(
        "--identify", action="store_true", help="identify the detected stars once (as bench_realsky.py does)"
    )
    parser.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two --rows files and stop")
    args = parser.parse_args()
    if args.compare:
        _compare(*args.compare)
        return
    import hostlink

    paths = _paths(args.set)
    options = _options(args.set)
    seconds, result = _time(paths, options, args.repeat)
    print(f"tree {Path(hostlink.__file__).parent.parent}: {len(paths)} frames, {result.session.x_px.size} rows")
    print("centroid_images CPU [s]: " + " ".join(f"{s:.3f}" for s in seconds) + f"  (min {min(seconds):.3f})")
    if args.rows:
        text = {f"text_{name}": np.asarray(column, dtype=str) for name, column in result.session.extra.items()}
        np.savez(args.rows, **_rows(paths, options), **text, text_mag=np.asarray(result.session.mag, dtype=str))
    if args.identify:
        _identify_once(result, args.set)


if __name__ == "__main__":
    main()
