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

Per frame: stars each identified; of the solver's stars, how many we identify, counted two ways side by side: by
position (a centroid of ours within :data:`SAME_STAR_PX` carrying the same identity; of those named differently, how
many name the other star of an unresolved pair, the same detection) and by identity (the solver's catalogue star named
by one of our rows of the frame, wherever its centroid; how many of those lie beyond SAME_STAR_PX); the solver given
our centroids, whose names are compared with ours star by star; and each side's residual on its own centroids through
its own calibrated camera, the attitude fitted per frame (Markley's SVD) [px and arcsec].
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

#: The directory holding the image sets (docs/realsky.md): not in the repository, named by the environment.
SHARED = Path(os.environ["STARTRACKER_REALSKY_ROOT"]) if "STARTRACKER_REALSKY_ROOT" in os.environ else None
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


@dataclass(frozen=True)
class _Ours:
    """Our side of one set: the identification (iterative, with the admission) and the detected stars alone."""

    ident: object
    detected: object
    once: object
    times: dict


def _run_ours(paths: list[Path], image_set: ImageSet, nominal, candidates: bool, cache) -> _Ours:
    """Images -> identified stars, ours, in process (CPU seconds of each stage); ``cache``: the catalogue's indexes,
    pair tables and pattern database (``PairCache``), built before the timing as the solver's database is."""
    from hostlink.images.centroid import CentroidOptions, TimeOptions, centroid_images
    from hostlink.images.guided import candidate_rows
    from hostlink.images.identify import identify_iteratively, identify_session

    options = CentroidOptions(threshold_sigma=image_set.threshold_sigma, median_of_inputs=image_set.median_of_inputs)
    if not candidates:  # the detected stars alone: no guided admission (the figures before it)
        options = replace(options, candidate_sigma=None)
    t0 = time.process_time()
    cent = centroid_images(paths, options, TimeOptions(time_unknown=True))
    t1 = time.process_time()
    detected = cent.session.select(~candidate_rows(cent.session))  # the faint candidates are only for ..._iteratively
    once = identify_session(detected, nominal, cache=cache)
    t2 = time.process_time()
    ident = identify_iteratively(cent.session, nominal, cache=cache)
    t3 = time.process_time()
    times = {"ours_centroid": t1 - t0, "ours_identify_once": t2 - t1, "ours_identify_iterative": t3 - t2}
    return _Ours(ident, detected, once, times)


def _run_solver(paths: list[Path], database, fov: float, nominal, detected) -> tuple[list, object, object, float]:
    """The solver from the images (its extractor and solve, timed), its calibration of what it solved, and its
    calibration given our detected centroids (brightest first) instead of its own: (solutions, calibration,
    calibration on ours, CPU seconds)."""
    from hostlink.images import solver_adapter
    from hostlink.images.read import read_image

    width, height = nominal.image_size_px
    pixels = [read_image(p).pixels for p in paths]
    t4 = time.process_time()
    engine = [solver_adapter.engine_solve_image(database, image, fov) for image in pixels]
    t5 = time.process_time()
    x0, y0 = nominal.principal_point_px
    frames = [(e.x_px - x0, e.y_px - y0, e.brightness) for e in engine]
    engine_cal = solver_adapter.engine_calibration(database, frames, (width, height), fov)
    starts = detected.frame_starts
    ours_frames = []
    for k in range(len(paths)):
        a, b = int(starts[k]), int(starts[k + 1])
        order = a + np.argsort(detected.mag[a:b], kind="stable")
        flux = 10.0 ** (-0.4 * detected.mag[order])
        ours_frames.append((detected.x_px[order] - x0, detected.y_px[order] - y0, flux))
    engine_on_ours = solver_adapter.engine_calibration(database, ours_frames, (width, height), fov)
    return engine, engine_cal, engine_on_ours, t5 - t4


def _solver_on_our_names(ours: _Ours, engine_on_ours, catalogue, focal_px: float) -> dict:
    """The solver given our detected centroids: of the stars it names, how many we name the same, differently (and
    of those, the other star of an unresolved pair) and not at all; the same centroids, so by identity and position
    at once (the measure for a set whose images the solver's own extractor finds nothing in)."""
    out = dict.fromkeys(("stars", "same", "different", "different_unresolved_pair", "unnamed"), 0)
    if engine_on_ours is None:
        return out
    detected, session = ours.detected, ours.ident.session
    starts = detected.frame_starts
    # our detected rows in the final session, in its order (the candidates follow each frame's detected stars)
    from hostlink.images.guided import candidate_rows

    final = np.flatnonzero(~candidate_rows(session))
    for k, i, hip in engine_on_ours.matched_rows:
        a, b = int(starts[k]), int(starts[k + 1])
        row = a + np.argsort(detected.mag[a:b], kind="stable")[i]  # the frames were given brightest first
        ours_hip = int(session.star_id[final[row]])
        out["stars"] += 1
        if ours_hip == 0:
            out["unnamed"] += 1
        elif ours_hip == hip:
            out["same"] += 1
        else:
            out["different"] += 1
            out["different_unresolved_pair"] += _unresolved_pair(catalogue, ours_hip, hip, focal_px)
    return out


def _unresolved_pair(catalogue, hip_a: int, hip_b: int, focal_px: float) -> bool:
    """The two catalogue stars lie within hostlink.images.blends.UNRESOLVED_PX of each other on the detector."""
    from hostlink.images.blends import UNRESOLVED_PX

    r = _directions(catalogue, np.array([hip_a, hip_b], dtype=np.int64))
    return float(np.arccos(np.clip(r[0] @ r[1], -1.0, 1.0))) * focal_px <= UNRESOLVED_PX


def _compare_solver_stars(session, a: int, b: int, e, catalogue, focal_px: float) -> dict:
    """One frame's solver stars against our rows ``a:b``, two ways side by side. By position (the measure of the
    tables so far): our centroid nearest to the solver's, within :data:`SAME_STAR_PX`: named the same, named
    differently (and of those, how many name the other star of an unresolved pair: the same detection), left
    unnamed, or no centroid of ours there. By identity: the solver's catalogue star is named by one of our rows of
    the frame, wherever its centroid (and of those, how many lie beyond SAME_STAR_PX of the solver's centroid)."""
    sid = session.star_id[a:b]
    out = dict.fromkeys(("agree", "disagree", "disagree_pair", "missed", "undetected", "by_identity", "far"), 0)
    ex, ey = e.x_px[e.rows], e.y_px[e.rows]
    d = np.hypot(session.x_px[a:b][:, None] - ex[None], session.y_px[a:b][:, None] - ey[None])
    for j in range(e.rows.size):
        i = int(np.argmin(d[:, j])) if d.shape[0] else -1
        if i < 0 or d[i, j] > SAME_STAR_PX:
            out["undetected"] += 1
        elif sid[i] == 0:
            out["missed"] += 1
        elif sid[i] == e.hip[j]:
            out["agree"] += 1
        else:
            out["disagree"] += 1
            out["disagree_pair"] += _unresolved_pair(catalogue, int(sid[i]), int(e.hip[j]), focal_px)
        ours = np.flatnonzero(sid == e.hip[j])
        if ours.size:
            out["by_identity"] += 1
            out["far"] += bool(np.min(d[ours, j]) > SAME_STAR_PX)
    return out


def _frame_row(
    path: Path, k: int, ours: _Ours, engine, engine_cal, theta, catalogue, scored: list, principal_point_px
) -> dict:
    """One frame's figures (module docstring); appends our camera scored on the solver's stars to ``scored``."""
    from hostlink.images import solver_adapter
    from hostlink.images.guided import candidate_rows
    from onboard.camera import pixels_to_unit

    session = ours.ident.session
    a, b = int(session.frame_starts[k]), int(session.frame_starts[k + 1])
    sid = session.star_id[a:b]
    faint = candidate_rows(session)[a:b]
    named = (sid != 0) & ~faint  # the detected stars (the admitted faint ones apart)
    every = sid != 0

    def rms(rows: np.ndarray) -> float:
        if np.count_nonzero(rows) < 3:
            return math.nan
        bvec = pixels_to_unit(session.x_px[a:b][rows], session.y_px[a:b][rows], theta)
        return _frame_rms_rad(bvec, _directions(catalogue, sid[rows]))

    ours_rms, ours_all_rms = rms(named), rms(every)
    e = engine[k]
    counts = dict.fromkeys(("agree", "disagree", "disagree_pair", "missed", "undetected", "by_identity", "far"), 0)
    engine_rms = math.nan
    if e.solved:
        counts = _compare_solver_stars(session, a, b, e, catalogue, float(theta[0]))
        ex, ey = e.x_px[e.rows], e.y_px[e.rows]
        x0, y0 = principal_point_px  # the solver's frames are centred on the nominal's
        if engine_cal is not None and e.rows.size >= 3:
            bvec = solver_adapter.engine_pixels_to_unit(engine_cal, ex - x0, ey - y0)
            engine_rms = _frame_rms_rad(bvec, _directions(catalogue, e.hip))
        if e.rows.size >= 3:  # our camera scored on the solver's own stars (its centroids and names)
            ours_on_solver = _frame_rms_rad(pixels_to_unit(ex, ey, theta), _directions(catalogue, e.hip))
            scored.append((ours_on_solver, engine_rms, e.rows.size))
    return {
        "frame": path.name,
        "ours_identified": int(np.count_nonzero(named)),
        "solver_identified": int(e.rows.size),
        "solver_stars_we_identify": counts["agree"],
        "solver_stars_we_name_differently": counts["disagree"],
        "solver_stars_we_name_differently_unresolved_pair": counts["disagree_pair"],
        "solver_stars_we_leave_unnamed": counts["missed"],
        "solver_stars_we_do_not_keep": counts["undetected"],
        "solver_stars_we_name_by_identity": counts["by_identity"],
        "solver_stars_we_name_by_identity_beyond_same_star_px": counts["far"],
        "ours_rms_px": ours_rms * theta[0],
        "ours_rms_arcsec": ours_rms * ARCSEC_PER_RAD,
        "ours_with_faint_rms_px": ours_all_rms * theta[0],
        "ours_faint_admitted": int(np.count_nonzero(every & faint)),
        "solver_rms_px": engine_rms * (engine_cal.focal_px if engine_cal else math.nan),
        "solver_rms_arcsec": engine_rms * ARCSEC_PER_RAD,
    }


#: The per-frame counts summed into the set's summary.
_SUMMED = (
    "solver_stars_we_identify",
    "solver_stars_we_name_differently",
    "solver_stars_we_name_differently_unresolved_pair",
    "solver_stars_we_leave_unnamed",
    "solver_stars_we_do_not_keep",
    "solver_stars_we_name_by_identity",
    "solver_stars_we_name_by_identity_beyond_same_star_px",
)


def run_set(image_set: ImageSet, log=print, candidates: bool = True) -> dict:
    """One image set, ours and the solver's side by side (module docstring): the summary, printed through ``log``."""
    from hostlink.calibration.run import calibrate_session
    from hostlink.files.params import params_from_dict
    from hostlink.images import solver_adapter
    from hostlink.images.centroid import CentroidOptions, TimeOptions, centroid_images
    from hostlink.images.identify import identify_session, prepare_cache
    from hostlink.sky.catalogue import load_catalogue

    if SHARED is None:
        raise SystemExit("the real frames are not in the repository: set STARTRACKER_REALSKY_ROOT (docs/realsky.md)")
    paths = sorted((SHARED / image_set.name).glob(image_set.pattern))
    if not paths:
        raise SystemExit(f"{SHARED / image_set.name}: no {image_set.pattern}")
    nominal = params_from_dict(image_set.nominal)
    catalogue = load_catalogue()
    fov = solver_adapter.horizontal_fov_deg(nominal.focal_length_px, nominal.image_size_px[0])
    database = solver_adapter.pattern_database(catalogue, fov)  # loaded before any timing, for both
    cache = prepare_cache(nominal, catalogue)  # our database, built before the timing as the solver's is loaded
    first = centroid_images(paths[:1], CentroidOptions(), TimeOptions(time_unknown=True)).session
    identify_session(first, nominal, cache=cache)

    ours = _run_ours(paths, image_set, nominal, candidates, cache)
    engine, engine_cal, engine_on_ours, solver_s = _run_solver(paths, database, fov, nominal, ours.detected)
    # our camera: calibrated on the final identities (the default method), our residual per frame through it
    outcome, _ = calibrate_session(ours.ident.session, ours.ident.camera or nominal, keep_failed=True)
    theta = outcome.params.model_vector(np.float64)
    scored = []  # per frame: (our camera, the solver's camera) on the solver's stars [rad], and their number
    rows_out = [
        _frame_row(path, k, ours, engine, engine_cal, theta, catalogue, scored, nominal.principal_point_px)
        for k, path in enumerate(paths)
    ]
    summary = {
        "set": image_set.name,
        "frames": len(paths),
        "ours_frames_identified": ours.ident.n_frames_identified,
        "solver_frames_solved": sum(e.solved for e in engine),
        "ours_stars": ours.ident.n_identified,
        "solver_stars": sum(r["solver_identified"] for r in rows_out),
        **{name: sum(r[name] for r in rows_out) for name in _SUMMED},
        "ours_calibrated_rms_px": outcome.after.get("rms_px"),
        "on_the_solvers_stars_arcsec": _pooled(scored),
        "solver_calibrated_rmse_px": None if engine_cal is None else engine_cal.rmse_px,
        "solver_on_our_centroids": None
        if engine_on_ours is None
        else {
            "frames_solved": engine_on_ours.n_frames,
            "stars": len(engine_on_ours.matched),
            "calibrated_rmse_px": engine_on_ours.rmse_px,
            "names": _solver_on_our_names(ours, engine_on_ours, catalogue, float(theta[0])),
        },
        "rounds": list(ours.ident.rounds),
        "time_s": {**ours.times, "solver_extract_and_solve": solver_s},
        "per_frame": rows_out,
    }
    _print(summary, ours.once.n_identified, log)
    return summary


def _print(s: dict, once: int, log) -> None:
    """The set's summary ``s`` through ``log``: the per-frame table, the stars against the solver's, the residuals,
    the times and the identification rounds (``once``: our stars after one round)."""
    log(f"== {s['set']}: {s['frames']} frames")
    _print_frames(s["per_frame"], log)
    _print_stars(s, once, log)
    _print_residuals(s, log)
    _print_time_and_rounds(s["time_s"], s["rounds"], log)


def _print_frames(per_frame: list[dict], log) -> None:
    """One line per frame: stars identified by us (and faint ones admitted) and the solver, and the residuals."""
    log(
        f"{'frame':34s} {'ours':>5s} {'faint':>5s} {'solver':>6s} {'both':>5s} {'differ':>6s} {'ours px':>8s} "
        f"{'+faint px':>9s} {'solver px':>9s} {'by id':>5s}"
    )
    for r in per_frame:
        log(
            f"{r['frame']:34s} {r['ours_identified']:5d} {r['ours_faint_admitted']:5d} {r['solver_identified']:6d} "
            f"{r['solver_stars_we_identify']:5d} {r['solver_stars_we_name_differently']:6d} "
            f"{r['ours_rms_px']:8.3f} {r['ours_with_faint_rms_px']:9.3f} {r['solver_rms_px']:9.3f} "
            f"{r['solver_stars_we_name_by_identity']:5d}"
        )


def _print_stars(s: dict, once: int, log) -> None:
    """The set's frames and stars, ours against the solver's, by position and by identity."""
    share = s["solver_stars_we_identify"] / s["solver_stars"] if s["solver_stars"] else math.nan
    log(
        f"frames: ours {s['ours_frames_identified']}, solver {s['solver_frames_solved']}; "
        f"stars: ours {s['ours_stars']} (one round {once}), solver {s['solver_stars']}; of the solver's we identify "
        f"{s['solver_stars_we_identify']} ({100 * share:.1f} %), name differently "
        f"{s['solver_stars_we_name_differently']}, leave unnamed {s['solver_stars_we_leave_unnamed']}, have no "
        f"centroid for {s['solver_stars_we_do_not_keep']} (by position: our centroid within {SAME_STAR_PX:g} px; of "
        f"the named differently, {s['solver_stars_we_name_differently_unresolved_pair']} name the other star of an "
        "unresolved pair)"
    )
    by_id = s["solver_stars_we_name_by_identity"]
    log(
        f"by identity (the solver's catalogue star named by one of our rows of the frame, wherever): {by_id} "
        f"({100 * by_id / s['solver_stars'] if s['solver_stars'] else math.nan:.1f} %), of them "
        f"{s['solver_stars_we_name_by_identity_beyond_same_star_px']} with our centroid beyond {SAME_STAR_PX:g} px"
    )


def _print_residuals(s: dict, log) -> None:
    """The calibrated residuals, ours and the solver's, each camera scored on the solver's stars, and the solver run
    on our centroids."""
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
        n = on_ours["names"]
        log(
            f"  of the {n['stars']} it names we name {n['same']} the same, {n['different']} differently "
            f"({n['different_unresolved_pair']} the other star of an unresolved pair), {n['unnamed']} not at all"
        )


def _print_time_and_rounds(t: dict, rounds: list[dict], log) -> None:
    """The times [s] of our stages and the solver's, then each identification round's stars."""
    log(
        f"time: ours centroid {t['ours_centroid']:.2f} s + identify {t['ours_identify_once']:.2f} s (iterative "
        f"with calibration {t['ours_identify_iterative']:.2f} s); solver extract + solve "
        f"{t['solver_extract_and_solve']:.2f} s"
    )
    for r in rounds:
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
