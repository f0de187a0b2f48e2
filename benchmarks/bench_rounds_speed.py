"""Benchmark: ``identify_iteratively``'s rounds (issue 30: identify, calibrate, identify again), on a real set's
session (centroids computed once and saved: ``bench_identify_speed.py prepare``) or on the rendered 50-deg field of
tests/test_identify_field_widths.py, with the catalogue's tables built before the timing (``prepare_cache``), so
that two trees can be timed side by side, alternately, on the same input; the figures of docs/realsky.md's speed
part.

    # once: the inputs (a real set as bench_identify_speed.py prepares it; the rendered 50-deg field)
    PYTHONPATH=. .venv/bin/python benchmarks/bench_identify_speed.py prepare --set granasat --session G.parquet
    PYTHONPATH=. .venv/bin/python benchmarks/bench_rounds_speed.py render --session W.parquet
    # per tree, alternately: CPU seconds of identify_iteratively (time.process_time), and the identities, the rounds'
    # records and the returned camera (with the 1-sigma of a full calibration of the result) written to OUT
    PYTHONPATH=TREE .venv/bin/python benchmarks/bench_rounds_speed.py run --set granasat --session G.parquet \
        --repeat 2 --json OUT.json
    # the trees compared: identities, the rounds' records' counts, the returned camera's difference in its 1-sigma,
    # the speed ratio
    .venv/bin/python benchmarks/bench_rounds_speed.py compare BEFORE.json AFTER.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_realsky's image sets

#: The rendered wide field: tests/test_identify_field_widths.py's 50-deg lens (3 % barrel at the corner), its
#: nominal 5 % long without distortion, identified to Hp 7.5 (its ``ID_MAGLIM``).
WIDE_FOV_DEG = 50.0
WIDE_CORNER_FRACTION = 0.03
WIDE_FRAMES = 3
WIDE_MAGLIM = 7.5
WIDE_FOCAL_ERROR = 0.05


def _wide_cameras():
    from hostlink.sky.simulate import seed004_camera
    from onboard.params import Distortion

    base = seed004_camera()
    width, height = base.image_size_px
    focal_mm = 0.5 * width * base.pixel_pitch_um * 1e-3 / math.tan(math.radians(0.5 * WIDE_FOV_DEG))
    half_diagonal_px = 0.5 * math.hypot(width, height)
    camera = replace(
        base, focal_length_mm=focal_mm, distortion=Distortion(k1=-WIDE_CORNER_FRACTION / half_diagonal_px**2)
    )
    nominal = replace(camera, distortion=Distortion(), focal_length_mm=focal_mm * (1.0 + WIDE_FOCAL_ERROR))
    return camera, nominal


def _render(out: Path) -> None:
    """The 50-deg field rendered and centroided as tests/test_identify_field_widths.py's rendered test does."""
    from hostlink.files.session import Session, write_session
    from hostlink.images.centroid import centroid_pixels
    from hostlink.sky.render import RenderConfig, render_frame
    from hostlink.sky.simulate import SimConfig, simulate

    camera, _ = _wide_cameras()
    sim = simulate(
        SimConfig(camera=camera, frames=WIDE_FRAMES, noise_px=0.0, min_stars=8, max_stars=100_000, maglim=6.5, seed=7)
    )
    cols: dict[str, list] = {"frame": [], "x": [], "y": [], "mag": []}
    for k in range(WIDE_FRAMES):
        rendered = render_frame(sim, k, RenderConfig(seed=3))
        det = centroid_pixels(rendered.image_adu, saturation_adu=rendered.config.saturation_adu)
        cols["frame"].append(np.full(det.x_px.size, k, dtype=np.int64))
        cols["x"].append(det.x_px)
        cols["y"].append(det.y_px)
        cols["mag"].append(det.mag)
    frame = np.concatenate(cols["frame"])
    t0 = sim.session.t_utc[sim.session.frame_starts[:-1]]
    session = Session(
        frame=frame,
        t_utc=np.asarray(t0[frame], dtype=object),
        star_id=np.zeros(frame.size, dtype=np.int64),
        x_px=np.concatenate(cols["x"]),
        y_px=np.concatenate(cols["y"]),
        mag=np.concatenate(cols["mag"]),
    )
    write_session(out, session)
    print(f"wide{WIDE_FOV_DEG:g}: {len(session)} rows in {session.n_frames} frames -> {out}")


def _nominal_and_maglim(set_name: str):
    if set_name == "wide50":
        return _wide_cameras()[1], WIDE_MAGLIM
    from bench_realsky import SETS

    from hostlink.files.params import params_from_dict

    return params_from_dict(SETS[set_name].nominal), None


def _run(set_name: str, session_path: Path, repeat: int, out: Path | None) -> None:
    import hostlink
    from hostlink.calibration.run import calibrate_session
    from hostlink.files.session import read_session
    from hostlink.images.identify import identify_iteratively, prepare_cache
    from hostlink.sky.catalogue import load_catalogue

    nominal, maglim = _nominal_and_maglim(set_name)
    session = read_session(session_path)
    catalogue = load_catalogue()
    cache = prepare_cache(nominal, catalogue, maglim)  # built before the timing, as a solver's database is
    identify_iteratively(session, nominal, catalogue, maglim, cache=cache)  # warm: imports, lazy loads
    seconds = []
    for _ in range(repeat):
        t0 = time.process_time()
        ident = identify_iteratively(session, nominal, catalogue, maglim, cache=cache)
        seconds.append(time.process_time() - t0)
    camera = ident.camera
    # the returned camera's 1-sigma: that of the calibration the user runs on the result (not timed)
    full, _ = calibrate_session(ident.session, nominal, keep_failed=True, mirror_fit=False)
    result = {
        "tree": str(Path(hostlink.__file__).resolve().parent.parent),
        "set": set_name,
        "identify_iteratively_s": seconds,
        "identified": ident.n_identified,
        "star_id": [ident.session.star_id[s].tolist() for s in ident.session.frame_slices()],
        "camera": None if camera is None else camera.model_vector(np.float64).tolist(),
        "camera_sigma": _model_sigma(full),
        "rounds": [{k: v for k, v in r.items() if k not in ("calibration", "focal_length_px")} for r in ident.rounds],
        "rounds_focal_px": [r["focal_length_px"] for r in ident.rounds],
    }
    print(
        f"{result['tree']} {set_name}: identify_iteratively min {min(seconds):.3f} s "
        f"{[round(s, 3) for s in seconds]}; identified {ident.n_identified}; rounds "
        f"{[(r['stars_identified'], r['kept']) for r in ident.rounds]}"
    )
    if out is not None:
        out.write_text(json.dumps(result))


def _model_sigma(outcome) -> list[float]:
    """The 1-sigma of every model-vector slot (f in px first, as ``model_vector`` and the covariance; 0 for a
    parameter held)."""
    from onboard.params import ESTIMATE_NAMES

    sigma = np.zeros(len(ESTIMATE_NAMES))
    diag = np.sqrt(np.abs(np.diag(outcome.covariance)))
    for name, s in zip(outcome.estimate, diag, strict=True):
        sigma[ESTIMATE_NAMES.index(name)] = s
    return sigma.tolist()


def _counts(records):
    """The rounds' records without their measured figures (floats: focal lengths, expected false, sigmas): what
    was identified, added, lost, renamed, kept, searched and admitted."""
    if isinstance(records, dict):
        return {k: _counts(v) for k, v in records.items() if not isinstance(v, float)}
    if isinstance(records, list):
        return [_counts(v) for v in records]
    return records


def _compare(a_path: Path, b_path: Path) -> None:
    a, b = json.loads(a_path.read_text()), json.loads(b_path.read_text())
    same = {"star_id": a["star_id"] == b["star_id"], "rounds": _counts(a["rounds"]) == _counts(b["rounds"])}
    cam_a, cam_b, sigma = (np.array(v or []) for v in (a["camera"], b["camera"], a["camera_sigma"]))
    held = sigma == 0
    in_sigma = np.abs(cam_a - cam_b) / np.where(held, 1.0, sigma)
    in_sigma[held & (cam_a == cam_b)] = 0.0
    # every round's camera's focal length (the admission's among them), in the returned camera's f 1-sigma
    focal = np.abs(np.subtract(a["rounds_focal_px"], b["rounds_focal_px"])) / (sigma[0] if sigma[0] else 1.0)
    ratio = min(a["identify_iteratively_s"]) / min(b["identify_iteratively_s"])
    print(
        f"{a['set']}: identities equal {same['star_id']}, rounds equal {same['rounds']}; camera differs by at most "
        f"{np.max(in_sigma) if in_sigma.size else 0.0:.2e} sigma, the rounds' focal lengths by at most "
        f"{np.max(focal) if focal.size else 0.0:.2e} sigma; speed-up (min CPU s) {ratio:.2f}x "
        f"({min(a['identify_iteratively_s']):.3f} / {min(b['identify_iteratively_s']):.3f} s)"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render")
    render.add_argument("--session", type=Path, required=True)
    run = sub.add_parser("run")
    run.add_argument("--set", default="granasat", help="granasat, openstartracker or wide50")
    run.add_argument("--session", type=Path, required=True)
    run.add_argument("--repeat", type=int, default=2)
    run.add_argument("--json", type=Path)
    compare = sub.add_parser("compare")
    compare.add_argument("a", type=Path)
    compare.add_argument("b", type=Path)
    args = parser.parse_args()
    from hostlink.errors import UserError

    try:
        if args.command == "render":
            _render(args.session)
        elif args.command == "run":
            _run(args.set, args.session, args.repeat, args.json)
        else:
            _compare(args.a, args.b)
    except (UserError, OSError, json.JSONDecodeError, KeyError) as exc:  # a missing or wrong file: one line
        print(f"bench_rounds_speed: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
