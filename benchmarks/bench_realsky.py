"""Benchmark: real night-sky images -> identified stars per frame, the project in process against tetra3rs from the
same images, side by side in one run (issue 30); the figures of docs/realsky.md.

Per image set (the shared folders: granasat, nine 1280 x 960 JPEG frames of a ~27 deg camera; openstartracker, ten
1392 x 1040 PNG frames of a ~6 deg camera), with the time unknown:

- ours: ``centroid_images`` (the defaults; openstartracker against the median of its frames at 3 sigma, as
  scripts/realsky.py) then ``identify_iteratively`` (identify, calibrate, identify again until nothing new), timed
  separately, in process;
- tetra3rs: its own source extractor and lost-in-space solve on each image (``solver_adapter.engine_solve_image``,
  pattern database loaded first, as ours), timed; then its own multi-image calibration (radial model) of the frames
  it solved (``solver_adapter.engine_calibration``).

Per frame: stars each identified; of the solver's stars, how many we identify (a centroid of ours within
:data:`SAME_STAR_PX` carrying an identity) and how many of those we name differently; and each side's residual on
its own centroids through its own calibrated camera, the attitude fitted per frame (Markley's SVD) [px and arcsec].
Times are CPU seconds of this process (time.process_time: the machine may be shared), database loaded first.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_realsky.py [--set granasat|openstartracker|all] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

SHARED = Path(os.environ.get("STARTRACKER_REALSKY_ROOT", "/work/shared/realsky"))
#: A centroid of ours and one of the solver's are the same star when this close [px] (the two extractors differ by
#: ~0.1-0.3 px on clean stars, more on trailed ones).
SAME_STAR_PX = 2.0
ARCSEC_PER_RAD = 206264.80624709636


@dataclass(frozen=True)
class ImageSet:
    name: str
    pattern: str
    nominal: dict
    median_of_inputs: bool = False
    threshold_sigma: float = 5.0


SETS = {
    # the source repository's own nominal (f 2657.33 px at 4.65 um, principal point (666, 440)): README of the folder
    "granasat": ImageSet(
        "granasat",
        "*.jpg",
        {
            "focal_length_mm": 2657.33 * 4.65e-3,
            "pixel_pitch_um": 4.65,
            "principal_point_px": [666.0, 440.0],
            "image_size_px": [1280, 960],
        },
    ),
    # scripts/realsky.py's nominal (85 mm at 6.45 um, centred) and centroiding (median of the frames, 3 sigma)
    "openstartracker": ImageSet(
        "openstartracker",
        "img*.png",
        {
            "focal_length_mm": 85.0,
            "pixel_pitch_um": 6.45,
            "principal_point_px": [695.5, 519.5],
            "image_size_px": [1392, 1040],
        },
        median_of_inputs=True,
        threshold_sigma=3.0,
    ),
}


def _frame_rms_rad(b: np.ndarray, r: np.ndarray) -> float:
    """RMS |b - C r| [rad] of one frame's stars with C fitted to them (Markley's SVD): NaN under 3 stars."""
    from onboard.attitude import DegenerateGeometry, attitude_from_vectors, residuals_rad

    if b.shape[0] < 3:
        return math.nan
    try:
        c = attitude_from_vectors(b, r)
    except DegenerateGeometry:
        return math.nan
    return float(np.sqrt(np.mean(residuals_rad(b, r, c) ** 2)))


def _pooled(scored: list[tuple[float, float, int]]) -> dict | None:
    """RMS over every frame's stars [arcsec] of per-frame RMS figures (ours, the solver's) weighted by star count."""
    if not scored:
        return None
    ours, solver, n = (np.array(v, dtype=np.float64) for v in zip(*scored, strict=True))
    keep = np.isfinite(ours) & np.isfinite(solver)
    if not np.any(keep):
        return None

    def pool(v: np.ndarray) -> float:
        return float(np.sqrt(np.sum(n[keep] * v[keep] ** 2) / np.sum(n[keep]))) * ARCSEC_PER_RAD

    return {"stars": int(np.sum(n[keep])), "our_camera": pool(ours), "solver_camera": pool(solver)}


def _directions(catalogue, hip: np.ndarray) -> np.ndarray:
    from hostlink.sky.apparent import hip_lookup, stars_at_j2000
    from onboard.camera import radec_to_unit

    stars = stars_at_j2000(catalogue, hip_lookup(catalogue, hip))
    return radec_to_unit(stars.ra_rad, stars.dec_rad)


def run_set(image_set: ImageSet, log=print, candidates: bool = True) -> dict:
    from hostlink.calibration.run import calibrate_session
    from hostlink.files.params import params_from_dict
    from hostlink.images import solver_adapter
    from hostlink.images.centroid import CentroidOptions, TimeOptions, centroid_images
    from hostlink.images.guided import candidate_rows
    from hostlink.images.identify import identify_iteratively, identify_session
    from hostlink.images.read import read_image
    from hostlink.sky.catalogue import load_catalogue
    from onboard.camera import pixels_to_unit

    paths = sorted((SHARED / image_set.name).glob(image_set.pattern))
    if not paths:
        raise SystemExit(f"{SHARED / image_set.name}: no {image_set.pattern}")
    nominal = params_from_dict(image_set.nominal)
    catalogue = load_catalogue()
    width, height = nominal.image_size_px
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, width)
    database = solver_adapter.pattern_database(catalogue, fov)  # loaded before any timing, for both
    identify_session(centroid_images(paths[:1], CentroidOptions(), TimeOptions(time_unknown=True)).session, nominal)

    options = CentroidOptions(threshold_sigma=image_set.threshold_sigma, median_of_inputs=image_set.median_of_inputs)
    if not candidates:  # the detected stars alone: no guided admission (the figures before it)
        options = replace(options, candidate_sigma=None)
    t0 = time.process_time()
    cent = centroid_images(paths, options, TimeOptions(time_unknown=True))
    t1 = time.process_time()
    detected = cent.session.select(~candidate_rows(cent.session))  # the faint candidates are only for ..._iteratively
    once = identify_session(detected, nominal)
    t2 = time.process_time()
    ident = identify_iteratively(cent.session, nominal)
    t3 = time.process_time()

    pixels = [read_image(p).pixels for p in paths]
    t4 = time.process_time()
    engine = [solver_adapter.engine_solve_image(database, image, fov) for image in pixels]
    t5 = time.process_time()
    x0, y0 = nominal.principal_point_px
    frames = [(e.x_px - x0, e.y_px - y0, e.brightness) for e in engine]
    engine_cal = solver_adapter.engine_calibration(database, frames, (width, height), fov)
    # the solver given our centroids (brightest first) instead of its own: for a set its extractor finds nothing in
    starts = detected.frame_starts
    ours_frames = []
    for k in range(len(paths)):
        a, b = int(starts[k]), int(starts[k + 1])
        order = a + np.argsort(detected.mag[a:b], kind="stable")
        flux = 10.0 ** (-0.4 * detected.mag[order])
        ours_frames.append((detected.x_px[order] - x0, detected.y_px[order] - y0, flux))
    engine_on_ours = solver_adapter.engine_calibration(database, ours_frames, (width, height), fov)

    # our camera: calibrated on the final identities (the default method), our residual per frame through it
    outcome, _ = calibrate_session(ident.session, ident.camera or nominal, keep_failed=True)
    theta = outcome.params.model_vector(np.float64)
    session = ident.session
    starts = session.frame_starts
    faint = candidate_rows(session)
    rows_out = []
    scored = []  # per frame: (our camera, the solver's camera) on the solver's stars [rad], and their number
    for k, path in enumerate(paths):
        a, b = int(starts[k]), int(starts[k + 1])
        sid = session.star_id[a:b]
        named = (sid != 0) & ~faint[a:b]  # the detected stars (the admitted faint ones apart)
        ours_rms = ours_all_rms = math.nan
        if np.count_nonzero(named) >= 3:
            bvec = pixels_to_unit(session.x_px[a:b][named], session.y_px[a:b][named], theta)
            ours_rms = _frame_rms_rad(bvec, _directions(catalogue, sid[named]))
        every = sid != 0
        if np.count_nonzero(every) >= 3:
            bvec = pixels_to_unit(session.x_px[a:b][every], session.y_px[a:b][every], theta)
            ours_all_rms = _frame_rms_rad(bvec, _directions(catalogue, sid[every]))
        e = engine[k]
        agree = disagree = missed = undetected = 0
        engine_rms = math.nan
        if e.solved:
            ex, ey = e.x_px[e.rows], e.y_px[e.rows]
            d = np.hypot(session.x_px[a:b][:, None] - ex[None], session.y_px[a:b][:, None] - ey[None])
            for j in range(e.rows.size):
                i = int(np.argmin(d[:, j])) if d.shape[0] else -1
                if i < 0 or d[i, j] > SAME_STAR_PX:
                    undetected += 1
                elif sid[i] == 0:
                    missed += 1
                elif sid[i] == e.hip[j]:
                    agree += 1
                else:
                    disagree += 1
            if engine_cal is not None and e.rows.size >= 3:
                bvec = solver_adapter.engine_pixels_to_unit(engine_cal, ex - x0, ey - y0)
                engine_rms = _frame_rms_rad(bvec, _directions(catalogue, e.hip))
            if e.rows.size >= 3:  # our camera scored on the solver's own stars (its centroids and names)
                ours_on_solver = _frame_rms_rad(pixels_to_unit(ex, ey, theta), _directions(catalogue, e.hip))
                scored.append((ours_on_solver, engine_rms, e.rows.size))
        rows_out.append(
            {
                "frame": path.name,
                "ours_identified": int(np.count_nonzero(named)),
                "solver_identified": int(e.rows.size),
                "solver_stars_we_identify": agree,
                "solver_stars_we_name_differently": disagree,
                "solver_stars_we_leave_unnamed": missed,
                "solver_stars_we_do_not_keep": undetected,
                "ours_rms_px": ours_rms * theta[0],
                "ours_rms_arcsec": ours_rms * ARCSEC_PER_RAD,
                "ours_with_faint_rms_px": ours_all_rms * theta[0],
                "ours_faint_admitted": int(np.count_nonzero(every & faint[a:b])),
                "solver_rms_px": engine_rms * (engine_cal.focal_px if engine_cal else math.nan),
                "solver_rms_arcsec": engine_rms * ARCSEC_PER_RAD,
            }
        )
    solver_total = sum(r["solver_identified"] for r in rows_out)
    summary = {
        "set": image_set.name,
        "frames": len(paths),
        "ours_frames_identified": ident.n_frames_identified,
        "solver_frames_solved": sum(e.solved for e in engine),
        "ours_stars": ident.n_identified,
        "solver_stars": solver_total,
        "solver_stars_we_identify": sum(r["solver_stars_we_identify"] for r in rows_out),
        "solver_stars_we_name_differently": sum(r["solver_stars_we_name_differently"] for r in rows_out),
        "solver_stars_we_leave_unnamed": sum(r["solver_stars_we_leave_unnamed"] for r in rows_out),
        "solver_stars_we_do_not_keep": sum(r["solver_stars_we_do_not_keep"] for r in rows_out),
        "ours_calibrated_rms_px": outcome.after.get("rms_px"),
        "on_the_solvers_stars_arcsec": _pooled(scored),
        "solver_calibrated_rmse_px": None if engine_cal is None else engine_cal.rmse_px,
        "solver_on_our_centroids": None
        if engine_on_ours is None
        else {
            "frames_solved": engine_on_ours.n_frames,
            "stars": len(engine_on_ours.matched),
            "calibrated_rmse_px": engine_on_ours.rmse_px,
        },
        "rounds": list(ident.rounds),
        "time_s": {
            "ours_centroid": t1 - t0,
            "ours_identify_once": t2 - t1,
            "ours_identify_iterative": t3 - t2,
            "solver_extract_and_solve": t5 - t4,
        },
        "per_frame": rows_out,
    }
    _print(summary, once.n_identified, log)
    return summary


def _print(s: dict, once: int, log) -> None:
    t = s["time_s"]
    log(f"== {s['set']}: {s['frames']} frames")
    log(
        f"{'frame':34s} {'ours':>5s} {'faint':>5s} {'solver':>6s} {'both':>5s} {'differ':>6s} {'ours px':>8s} "
        f"{'+faint px':>9s} {'solver px':>9s}"
    )
    for r in s["per_frame"]:
        log(
            f"{r['frame']:34s} {r['ours_identified']:5d} {r['ours_faint_admitted']:5d} {r['solver_identified']:6d} "
            f"{r['solver_stars_we_identify']:5d} {r['solver_stars_we_name_differently']:6d} "
            f"{r['ours_rms_px']:8.3f} {r['ours_with_faint_rms_px']:9.3f} {r['solver_rms_px']:9.3f}"
        )
    share = s["solver_stars_we_identify"] / s["solver_stars"] if s["solver_stars"] else math.nan
    log(
        f"frames: ours {s['ours_frames_identified']}, solver {s['solver_frames_solved']}; "
        f"stars: ours {s['ours_stars']} (one round {once}), solver {s['solver_stars']}; of the solver's we identify "
        f"{s['solver_stars_we_identify']} ({100 * share:.1f} %), name differently "
        f"{s['solver_stars_we_name_differently']}, leave unnamed {s['solver_stars_we_leave_unnamed']}, have no "
        f"centroid for {s['solver_stars_we_do_not_keep']}"
    )
    solver_rmse = s["solver_calibrated_rmse_px"]
    log(
        f"calibrated residual: ours {s['ours_calibrated_rms_px']:.3f} px, solver "
        + ("(nothing solved)" if solver_rmse is None else f"{solver_rmse:.3f} px")
    )
    scored = s["on_the_solvers_stars_arcsec"]
    if scored:
        log(
            f"scored on the solver's {scored['stars']} stars (its centroids and names): our camera "
            f'{scored["our_camera"]:.2f}", the solver\'s {scored["solver_camera"]:.2f}"'
        )
    on_ours = s["solver_on_our_centroids"]
    if on_ours:
        log(
            f"the solver on our centroids: {on_ours['frames_solved']} frames, {on_ours['stars']} stars, calibrated "
            f"residual {on_ours['calibrated_rmse_px']:.3f} px"
        )
    log(
        f"time: ours centroid {t['ours_centroid']:.2f} s + identify {t['ours_identify_once']:.2f} s (iterative "
        f"with calibration {t['ours_identify_iterative']:.2f} s); solver extract + solve "
        f"{t['solver_extract_and_solve']:.2f} s"
    )
    for r in s["rounds"]:
        chance = (
            f" (expected by chance {r['expected_false']:.1f} of {r['searched']} searched; "
            f"{r['frames_declined']} frames admitted none: chance too high)"
            if "searched" in r
            else ""
        )
        log(
            f"  round {r['round']}: {r['stars_identified']} stars, +{r['added']} -{r['lost']} renamed {r['renamed']}"
            + chance
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", choices=(*SETS, "all"), default="all")
    parser.add_argument("--json", metavar="OUT", help="write the figures as JSON")
    parser.add_argument("--no-candidates", action="store_true", help="centroid without the faint candidates")
    args = parser.parse_args()
    chosen = list(SETS) if args.set == "all" else [args.set]
    results = [run_set(SETS[name], candidates=not args.no_candidates) for name in chosen]
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
