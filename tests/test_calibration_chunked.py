"""Batch calibration over chunks of frames: the same camera as the in-memory path, to rounding, however the frames
are split, from memory or from session files (several files, Parquet) through the chunked reader."""

import json
from dataclasses import replace

import numpy as np
import pytest
from synthetic_sessions import synthetic_session

from hostlink.calibration.bundle import BundleOptions, bundle_adjust
from hostlink.calibration.chunked import estimated_session_rows
from hostlink.calibration.data import (
    CalibrationData,
    chunk_frame_count,
    load_chunk,
    measured_directions,
    save_chunk,
    take_frames,
)
from hostlink.calibration.frames import triad_attitudes
from hostlink.calibration.model import attitude_terms, parameter_scales
from hostlink.calibration.passes import (
    PassRequest,
    chunk_pass,
    frame_attitudes,
    residual_histogram,
    robust_sigma_from_histogram,
)
from hostlink.calibration.robust import robust_sigma_2d
from hostlink.calibration.run import calibrate, calibrate_archive, calibrate_chunks, calibrate_session
from hostlink.calibration.source import ChunkSource, frames_of
from hostlink.cli import main
from hostlink.files.params import data_file, load_params
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate
from onboard.params import ESTIMATE_NAMES

SEED004 = load_params("builtin:seed004_camera")
SEED004_NOMINAL = load_params("builtin:seed004_nominal")
NOMINAL = str(data_file("seed004_nominal.json"))


def _split(data, cuts):
    """``data`` as chunks of whole frames between the frame indices ``cuts`` (first 0, last the frame count)."""
    return ChunkSource(tuple(frames_of(data, a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True)))


def assert_same_camera(a, b):
    """Same camera to rounding: 1e-9 relative (summation order over chunks: ~1e-12 seen) and 0.01 sigma."""
    cols = [ESTIMATE_NAMES.index(n) for n in a.estimate]
    assert a.estimate == b.estimate
    sigma = np.sqrt(np.diag(a.covariance))
    diff = np.abs(a.theta - b.theta)[cols]
    assert np.all(diff <= 1e-9 * np.abs(a.theta[cols]) + 1e-300) or np.all(diff < 1e-6 * sigma)
    assert np.all(diff < 0.01 * sigma)
    # the covariance from the same normal matrix summed in another order: 1e-6 relative covers its conditioning
    np.testing.assert_allclose(np.diag(b.covariance), np.diag(a.covariance), rtol=1e-6)
    assert a.rejected == b.rejected
    assert len(a.history) == len(b.history)


@pytest.fixture(scope="module")
def dirty():
    """300 frames of 10-30 stars with 3 % misidentified: voting and gating both act, frames of every size."""
    ss = synthetic_session(SEED004, 300, seed=3, misidentified_fraction=0.03)
    return ss, calibrate(ss.data, SEED004_NOMINAL)


@pytest.mark.parametrize(
    "cuts",
    [
        [0, 1, 2, 3, 300],  # single-frame chunks at the start
        [0, 8, 9, 57, 140, 141, 299, 300],  # uneven, single frames in the middle and at the end
        [0, 150, 300],  # two halves
        list(range(0, 301, 7)) + [300],  # many small chunks, a short last one
    ],
    ids=["single-first", "uneven", "halves", "every-7"],
)
def test_chunked_calibration_equals_the_in_memory_one_at_any_chunk_boundary(dirty, cuts):
    ss, whole = dirty
    cuts = sorted(set(cuts))
    assert_same_camera(whole, calibrate_chunks(_split(ss.data, cuts), SEED004_NOMINAL))


def test_chunks_split_where_a_frame_loses_all_its_stars_still_agree(dirty):
    """Boundaries right around the frames that voting or gating thin out, so a chunk may hold only a dropped frame."""
    ss, whole = dirty
    fidx = ss.data.frame_index()
    hit = np.unique(fidx[ss.misidentified])[:6]
    cuts = sorted({0, 300, *hit.tolist(), *(hit + 1).tolist()})
    assert_same_camera(whole, calibrate_chunks(_split(ss.data, cuts), SEED004_NOMINAL))


def test_in_memory_bundle_is_the_chunked_pass_on_one_chunk(dirty):
    ss, whole = dirty
    one = calibrate_chunks(ChunkSource((ss.data,)), SEED004_NOMINAL)
    np.testing.assert_array_equal(one.theta, whole.theta)  # the same code on the same chunk: bit for bit
    assert whole.data.n_obs == one.n_stars_used and whole.data.n_frames == one.n_frames_used


@pytest.mark.parametrize("which", ["all", "every-third", "first", "last", "none"])
def test_taking_frames_by_index_equals_selecting_their_rows(dirty, which):
    """The samples' gather (row ranges of the chosen frames) is the row selection with frames of at least one star,
    an empty frame (frame 1 here) left out by both."""
    d = dirty[0].data
    starts = d.frame_starts.copy()
    starts[2:] -= d.counts[1]  # frame 1 loses its stars
    keep = np.ones(d.n_obs, dtype=bool)
    keep[d.frame_starts[1] : d.frame_starts[2]] = False
    data = CalibrationData(
        d.x_px[keep], d.y_px[keep], d.r[keep], starts, d.frame_number, d.star_id[keep], d.source_rows()[keep]
    )
    assert data.counts[1] == 0
    frames = {
        "all": np.arange(data.n_frames),
        "every-third": np.arange(0, data.n_frames, 3),
        "first": np.array([0]),
        "last": np.array([data.n_frames - 1]),
        "none": np.zeros(0, dtype=np.int64),
    }[which]
    pick = np.zeros(data.n_frames, dtype=bool)
    pick[frames] = True
    expected = data.select(pick[data.frame_index()], min_stars=1)[0]
    got = take_frames(data, frames)
    for name in ("x_px", "y_px", "r", "frame_starts", "frame_number", "star_id", "row"):
        assert getattr(got, name).dtype == getattr(expected, name).dtype
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


def test_spooled_chunk_reads_back_the_same_arrays_and_its_frame_count(dirty, tmp_path):
    """A chunk written to the spool reads back array for array (values and dtypes), and its frame count is read
    from the frame starts alone."""
    data = frames_of(dirty[0].data, 17, 121)
    path = tmp_path / "chunk000000.spool"
    save_chunk(path, data)
    back = load_chunk(path)
    for name in ("x_px", "y_px", "r", "frame_starts", "frame_number", "star_id"):
        assert getattr(back, name).dtype == getattr(data, name).dtype
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name))
    np.testing.assert_array_equal(back.source_rows(), data.source_rows())
    assert chunk_frame_count(path) == data.n_frames == 104


@pytest.mark.parametrize("damage", ["cut-in-a-header", "cut-in-the-data", "bytes-after-it", "an-npz-archive"])
def test_damaged_spool_file_is_an_error_naming_it(dirty, tmp_path, damage):
    """A spool file cut short, with bytes after its arrays, or not a spool file at all: a ValueError naming it, not
    a numpy traceback or a chunk of wrong arrays."""
    path = tmp_path / "chunk000000.spool"
    save_chunk(path, frames_of(dirty[0].data, 0, 50))
    raw = path.read_bytes()
    if damage == "an-npz-archive":
        np.savez(path.with_suffix(".npz"), x_px=np.zeros(3))
        path.with_suffix(".npz").replace(path)
    else:
        damaged = {"cut-in-a-header": raw[:20], "cut-in-the-data": raw[: len(raw) // 2], "bytes-after-it": raw + b"\0"}
        path.write_bytes(damaged[damage])
    with pytest.raises(ValueError, match="chunk000000.spool: not a spooled calibration chunk"):
        load_chunk(path)


def test_final_sums_without_the_gated_stars_equal_a_pass_that_leaves_them_out(dirty):
    """The final pass's sums without its stars beyond the gate (only their frames summed again) are the pass that
    leaves those stars out: matrices to the rounding of the sums, the residuals' sums and maxima, counts and
    histogram exactly. 3 % misidentified stars not voted out: most frames hold one."""
    data = dirty[0].data
    cols = np.arange(10)
    scale = parameter_scales(SEED004)
    theta = SEED004.model_vector()
    final = PassRequest(theta, 0.05, cols, scale, np.zeros(0, dtype=np.int64), 3.0, 1000, True, 0.25)
    regated = chunk_pass(data, final).regated
    gated = np.sort(chunk_pass(data, final).over_gate)
    assert 100 < gated.size < data.n_obs // 2
    fresh = chunk_pass(data, replace(final, excluded_rows=gated))
    for name in ("s", "rhs", "s_unit", "u_diag_unit"):
        expected = getattr(fresh, name)
        np.testing.assert_allclose(getattr(regated, name), expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    for name in ("cost", "sum_e2", "sum_arcsec2"):
        assert getattr(regated, name) == pytest.approx(getattr(fresh, name), rel=1e-13)
    for name in ("n_obs", "n_frames", "max_e_px", "max_arcsec"):
        assert getattr(regated, name) == getattr(fresh, name)
    np.testing.assert_array_equal(regated.hist, fresh.hist)
    np.testing.assert_array_equal(np.sort(regated.over_gate), np.sort(fresh.over_gate))


def test_histogram_scale_matches_the_exact_median():
    """The robust scale from binned residual lengths, against the exact median of the same lengths: bins 0.25 %
    wide with log interpolation, 10^5 Rayleigh draws: agreement to 0.05 % (the sample's own median error is 0.4 %)."""
    rng = np.random.default_rng(1)
    norm = np.linalg.norm(rng.normal(scale=0.07, size=(100_000, 2)), axis=1)
    exact = robust_sigma_2d(norm)
    binned = robust_sigma_from_histogram(residual_histogram(norm[:40_000]) + residual_histogram(norm[40_000:]))
    assert abs(binned / exact - 1.0) < 5e-4


def _remaining_step_rad(data, theta, att):
    """|A^-1 J_phi^T e| per frame: the Gauss-Newton attitude step still left [rad]."""
    e, jp = attitude_terms(data.x_px, data.y_px, data.r, np.repeat(att, data.counts, axis=0), theta)
    starts = data.frame_starts[:-1]
    a = np.add.reduceat(np.einsum("nki,nkj->nij", jp, jp), starts, axis=0)
    g = np.add.reduceat(np.einsum("nki,nk->ni", jp, e), starts, axis=0)
    return np.linalg.norm(np.linalg.solve(a, g[:, :, None])[:, :, 0], axis=1)


def test_frame_attitudes_reach_each_frames_optimum():
    """The TRIAD start is off the whitened optimum by ~1e-4 rad (one star's noise over its lever arm); the one
    Gauss-Newton step squares that: at most 1e-8 rad is left, 1/500 of the attitude noise (0.05 px / 5850 px /
    sqrt(20 stars) ~ 2e-6 rad), which moves the camera step only at second order."""
    ss = synthetic_session(SEED004, 50, seed=9)
    d, theta = ss.data, SEED004.model_vector()
    start = triad_attitudes(measured_directions(d, theta), d.r, d.frame_starts)
    assert np.max(_remaining_step_rad(d, theta, start)) > 1e-5
    assert np.max(_remaining_step_rad(d, theta, frame_attitudes(d, theta))) < 1e-8


@pytest.fixture(scope="module")
def session_files(tmp_path_factory):
    """One simulated session (misidentified and false stars), whole and as two files of consecutive frames."""
    cfg = seed004_config(frames=80, seed=41)
    cfg = type(cfg)(**{**cfg.__dict__, "misid_fraction": 0.03, "false_star_fraction": 0.1})
    session = simulate(cfg).session
    folder = tmp_path_factory.mktemp("chunked")
    whole = folder / "whole.csv"
    write_session(whole, session)
    half = session.frame_starts[40]
    parts = {}
    for ext in ("csv", "parquet"):  # Parquet stores float64 exactly, CSV to 1e-6 px as the whole file
        parts[ext] = [folder / f"night1.{ext}", folder / f"night2.{ext}"]
        write_session(parts[ext][0], session.select(np.arange(half)))
        write_session(parts[ext][1], session.select(np.arange(half, len(session))))
    return session, whole, parts


def test_archive_of_several_files_gives_the_camera_of_the_whole_session(session_files):
    session, _, parts = session_files
    whole, _ = calibrate_session(session, SEED004_NOMINAL)
    chunked, refs = calibrate_archive([str(p) for p in parts["parquet"]], SEED004_NOMINAL, chunk_frames=9)
    assert_same_camera(whole, chunked)
    assert refs.n_unidentified > 0  # the false stars


def test_cli_calibrates_several_files_in_chunks(session_files, tmp_path):
    _, whole_path, parts = session_files
    out_whole, out_chunked = tmp_path / "whole.json", tmp_path / "chunked.json"
    assert main(["calibrate", str(whole_path), "--nominal", NOMINAL, "--out", str(out_whole), "--quiet"]) == 0
    args = [
        "calibrate",
        *map(str, parts["csv"]),
        "--nominal",
        NOMINAL,
        "--out",
        str(out_chunked),
        "--chunk-frames",
        "13",
    ]
    assert main([*args, "--quiet"]) == 0
    a, b = json.loads(out_whole.read_text()), json.loads(out_chunked.read_text())
    # 1e-9 relative: summation order only; sigma 1e-6 relative as in assert_same_camera
    assert b["focal_length_mm"] == pytest.approx(a["focal_length_mm"], rel=1e-9)
    assert b["principal_point_px"] == pytest.approx(a["principal_point_px"], rel=1e-9)
    assert b["sigma"]["focal_length_mm"] == pytest.approx(a["sigma"]["focal_length_mm"], rel=1e-6)
    assert b["n_rejected"] == a["n_rejected"]
    assert b["residuals"]["after"]["rms_px"] == pytest.approx(a["residuals"]["after"]["rms_px"], rel=1e-9)


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--method", "cosine"], "bundle only"),
        (["--rejected", "x.csv"], "read whole"),
        (["--chunk-frames", "0"], "--chunk-frames"),
        (["--dask-workers", "0", "--dask", "local"], "--dask-workers"),
    ],
)
def test_chunked_options_refuse_what_they_cannot_do_in_one_line(session_files, tmp_path, capsys, extra, needle):
    _, _, parts = session_files
    out = tmp_path / "r.json"
    code = main(["calibrate", *map(str, parts["csv"]), "--nominal", NOMINAL, "--out", str(out), *extra])
    assert code == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_chunked_fit_that_does_not_converge_writes_nothing_unless_kept(session_files, tmp_path, capsys):
    _, _, parts = session_files
    out = tmp_path / "r.json"
    args = ["calibrate", *map(str, parts["parquet"]), "--nominal", NOMINAL, "--out", str(out), "--max-iter", "1"]
    assert main([*args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "did not converge" in err and len(err.strip().splitlines()) == 1 and not out.exists()
    assert main([*args, "--quiet", "--keep-failed"]) == 2  # kept for inspection, still a failure
    result = json.loads(out.read_text())
    assert result["converged"] is False and "did not converge" in result["failed"]


def test_chunked_calibration_that_rejects_most_stars_fails(session_files, tmp_path, capsys):
    """Identifications (star id and reference direction) shuffled among the stars of 70 % of the frames: those
    frames' stars disagree with any camera, voting and gating drop them, and a camera fitted to the remaining
    minority is not written."""
    session, _, _ = session_files
    rng = np.random.default_rng(7)
    order = np.arange(len(session))
    for k, rows in enumerate(session.frame_slices()):
        ident = rows.start + np.flatnonzero(session.star_id[rows])
        if k % 10 < 7:
            order[ident] = rng.permutation(ident)
    cols = {c: getattr(session, c)[order] for c in ("star_id", "ra_deg", "dec_deg")}
    bad = tmp_path / "shuffled.parquet"
    write_session(bad, type(session)(**{**session.__dict__, **cols}))
    out = tmp_path / "r.json"
    code = main(["calibrate", str(bad), "--nominal", NOMINAL, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "were rejected" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_dask_option_without_address_is_a_local_cluster():
    from hostlink.cli import build_parser

    parser = build_parser()
    base = ["calibrate", "s.parquet", "--nominal", NOMINAL, "--out", "r.json"]
    assert parser.parse_args([*base, "--dask"]).dask == "local"
    assert parser.parse_args([*base, "--dask", "tcp://10.0.0.1:8786"]).dask == "tcp://10.0.0.1:8786"
    assert parser.parse_args(base).dask is None


def test_round_tolerances_leave_the_camera_within_their_remainder_of_the_minimum(dirty):
    """A round stops at a step below BundleOptions.step_tol = 0.02 sigma, or at one whose product with the contraction
    measured between the fit's steps is below remainder_tol = 0.005 sigma, and applies it: what is left is at most
    that product while the contraction does not grow (Gauss-Newton here converges superlinearly, so it shrinks).
    Bound 5e-3 sigma: remainder_tol itself (step_tol leaves ~4e-4 at the ~50-fold contraction seen here); half the
    0.01 sigma the issue allows between two paths."""
    ss, _ = dirty
    loose = bundle_adjust(ss.data, SEED004_NOMINAL)
    tight = bundle_adjust(ss.data, SEED004_NOMINAL, BundleOptions(step_tol=1e-7, remainder_tol=0.0))
    cols = [ESTIMATE_NAMES.index(n) for n in tight.estimate]
    sigma = np.sqrt(np.diag(tight.covariance))
    assert np.max(np.abs(loose.theta - tight.theta)[cols] / sigma) < 5e-3
    assert len(loose.history) < len(tight.history)  # the looser tolerances save passes


def test_one_csv_with_no_option_is_read_in_chunks_with_the_whole_sessions_camera(session_files, tmp_path, monkeypatch):
    """The default of the bundle method on one CSV is the chunked path (memory bounded by one chunk): the session is
    never read whole, and the camera, its sigma, the rejections (by reason too) are those of the session in memory."""
    _, whole_path, _ = session_files
    import hostlink.files.session as session_module

    # the same file read whole (the CSV holds the centroids to 1e-6 px: the in-memory session itself differs)
    expected, references = calibrate_session(session_module.read_session(whole_path), SEED004_NOMINAL)

    def whole_read(*_args, **_kwargs):
        raise AssertionError("the session was read whole")

    monkeypatch.setattr(session_module, "read_session", whole_read)
    out = tmp_path / "default.json"
    assert main(["calibrate", str(whole_path), "--nominal", NOMINAL, "--out", str(out), "--quiet"]) == 0
    got = json.loads(out.read_text())
    assert got["focal_length_mm"] == pytest.approx(expected.params.focal_length_mm, rel=1e-9)
    assert got["principal_point_px"] == pytest.approx(list(expected.params.principal_point_px), rel=1e-9)
    assert got["sigma"]["focal_length_mm"] == pytest.approx(expected.sigma()["focal_length_mm"], rel=1e-6)
    assert got["n_rejected"] == expected.rejected
    assert got["rejected_by_reason"] == expected.rejected_stars.counts()
    assert references.unknown_rows.size == got["references"]["unknown_star_ids"]


def test_row_estimate_from_the_file_size_is_close_for_csv_and_exact_for_parquet(session_files):
    """The reading progress bar's total: a Parquet file's row count from its metadata, a CSV file's from its size
    over the mean line length of its head (fixed-format columns: within 2 % here, where the 80 frames' ~1700 lines
    all fit in the sampled head, so the estimate is the line count up to rounding)."""
    session, whole_path, parts = session_files
    assert estimated_session_rows([str(p) for p in parts["parquet"]]) == len(session)
    assert estimated_session_rows(str(whole_path)) == pytest.approx(len(session), rel=0.02)
    assert estimated_session_rows(str(whole_path) + ".missing") is None
