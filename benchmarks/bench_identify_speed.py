"""Benchmark: identification alone (issue 30), ``identify_session`` on a real set's detected stars and
``identify_iteratively`` on its whole session (the faint candidates with it), from centroids computed once and saved,
so that two trees can be timed side by side on the same input; the figures of docs/realsky.md's speed part.

    # once: centroid a set (bench_realsky's options) into a session file
    PYTHONPATH=. .venv/bin/python benchmarks/bench_identify_speed.py prepare --set granasat --session S.parquet
    # per tree, alternately: CPU seconds of each call (time.process_time, the catalogue and the pattern database
    # loaded first), and the identities and camera written to OUT for comparing the trees
    PYTHONPATH=TREE .venv/bin/python benchmarks/bench_identify_speed.py run --set granasat --session S.parquet \
        --repeat 3 --json OUT.json
    # the two trees' identities (per frame, the hip of every row) and calibrated cameras compared
    .venv/bin/python benchmarks/bench_identify_speed.py compare A.json B.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_realsky's image sets


def _prepare(set_name: str, out: Path) -> None:
    from bench_realsky import SETS, SHARED

    from hostlink.files.session import write_session
    from hostlink.images.centroid import CentroidOptions, TimeOptions, centroid_images

    image_set = SETS[set_name]
    if SHARED is None:
        raise SystemExit("the real frames are not in the repository: set STARTRACKER_REALSKY_ROOT (docs/realsky.md)")
    paths = sorted((SHARED / image_set.name).glob(image_set.pattern))
    options = CentroidOptions(threshold_sigma=image_set.threshold_sigma, median_of_inputs=image_set.median_of_inputs)
    session = centroid_images(paths, options, TimeOptions(time_unknown=True)).session
    write_session(out, session)
    print(f"{set_name}: {len(session)} rows in {session.n_frames} frames -> {out}")


def _identities(session) -> list[list[int]]:
    return [session.star_id[s].tolist() for s in session.frame_slices()]


def _run(set_name: str, session_path: Path, repeat: int, out: Path | None) -> None:
    from bench_realsky import SETS

    import hostlink
    from hostlink.files.params import params_from_dict
    from hostlink.files.session import read_session
    from hostlink.images import solver_adapter
    from hostlink.images.guided import candidate_rows
    from hostlink.images.identify import identify_iteratively, identify_session
    from hostlink.sky.catalogue import load_catalogue

    nominal = params_from_dict(SETS[set_name].nominal)
    session = read_session(session_path)
    detected = session.select(~candidate_rows(session))
    catalogue = load_catalogue()
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, nominal.image_size_px[0])
    solver_adapter.pattern_database(catalogue, fov)  # loaded before any timing
    first = detected.select(np.arange(int(detected.frame_starts[1])))
    # warm: imports and lazy loads. Since the SkyIndex no catalogue index outlives a call: each timed call builds its
    # own, where a tree with the module caches reused the one this call filled (docs/realsky.md)
    identify_session(first, nominal, catalogue)
    once_s, iterative_s = [], []
    for _ in range(repeat):
        t0 = time.process_time()
        once = identify_session(detected, nominal, catalogue)
        t1 = time.process_time()
        ident = identify_iteratively(session, nominal, catalogue)
        t2 = time.process_time()
        once_s.append(t1 - t0)
        iterative_s.append(t2 - t1)
    camera = ident.camera
    result = {
        "tree": str(Path(hostlink.__file__).resolve().parent.parent),
        "set": set_name,
        "rows": len(session),
        "identify_session_s": once_s,
        "identify_iteratively_s": iterative_s,
        "once_identified": once.n_identified,
        "iterative_identified": ident.n_identified,
        "once_star_id": _identities(once.session),
        "iterative_star_id": _identities(ident.session),
        "camera": None if camera is None else camera.model_vector(np.float64).tolist(),
        "rounds": [{k: v for k, v in r.items() if k != "calibration"} for r in ident.rounds],
    }
    print(
        f"{result['tree']} {set_name}: identify_session min {min(once_s):.3f} s {once_s}, identify_iteratively "
        f"min {min(iterative_s):.3f} s {iterative_s}; identified {once.n_identified} / {ident.n_identified}"
    )
    if out is not None:
        out.write_text(json.dumps(result))


def _compare(a_path: Path, b_path: Path) -> None:
    a, b = json.loads(a_path.read_text()), json.loads(b_path.read_text())
    same = {key: a[key] == b[key] for key in ("once_star_id", "iterative_star_id", "rounds")}
    cam_a, cam_b = np.array(a["camera"] or []), np.array(b["camera"] or [])
    cam = float(np.max(np.abs(cam_a - cam_b) / np.maximum(np.abs(cam_a), 1e-300))) if cam_a.size else 0.0
    ratio_once = min(a["identify_session_s"]) / min(b["identify_session_s"])
    ratio_iter = min(a["identify_iteratively_s"]) / min(b["identify_iteratively_s"])
    print(f"identities equal: {same}; camera max relative difference {cam:.2e}")
    print(
        f"speed-up (min CPU s, {a['tree']} / {b['tree']}): identify_session {ratio_once:.2f}x, "
        f"identify_iteratively {ratio_iter:.2f}x"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    prepare = sub.add_parser("prepare")
    prepare.add_argument("--set", default="granasat")
    prepare.add_argument("--session", type=Path, required=True)
    run = sub.add_parser("run")
    run.add_argument("--set", default="granasat")
    run.add_argument("--session", type=Path, required=True)
    run.add_argument("--repeat", type=int, default=3)
    run.add_argument("--json", type=Path)
    compare = sub.add_parser("compare")
    compare.add_argument("a", type=Path)
    compare.add_argument("b", type=Path)
    args = parser.parse_args()
    from hostlink.errors import UserError

    try:
        if args.command == "prepare":
            _prepare(args.set, args.session)
        elif args.command == "run":
            _run(args.set, args.session, args.repeat, args.json)
        else:
            _compare(args.a, args.b)
    except (UserError, OSError, json.JSONDecodeError, KeyError) as exc:  # a missing or wrong file: one line
        print(f"bench_identify_speed: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
