"""``hostlink replay`` streams: the session read in chunks (hostlink.calibration.replay.replay_chunks), its trace
written as it goes (hostlink.files.trace.TraceWriter); the estimate and the trace are those of the in-memory path,
bit for bit, and memory does not grow with the number of frames."""

import json
import tracemalloc

import numpy as np
import pytest

from hostlink.calibration.replay import replay_chunks, replay_session
from hostlink.cli import main
from hostlink.errors import UserError
from hostlink.files.params import load_params
from hostlink.files.session import concatenate_sessions, read_session, read_session_chunks, write_session
from hostlink.files.trace import TRACE_COLUMNS, write_trace
from hostlink.sky.simulate import seed004_config, simulate

NOMINAL = "builtin:seed004_nominal"


@pytest.fixture(scope="module")
def session():
    return simulate(seed004_config(frames=24, seed=11)).session


def _assert_same_trace(a: dict, b: dict) -> None:
    for name in TRACE_COLUMNS:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        if x.dtype.kind == "f":
            assert np.array_equal(x, y, equal_nan=True), name
        else:
            assert list(x) == list(y), name


@pytest.mark.parametrize("precision", ["float32", "fixed"])
def test_replay_in_chunks_equals_the_in_memory_replay_bit_for_bit_at_every_chunk_size(session, precision):
    nominal = load_params(NOMINAL)
    whole = replay_session(session, nominal, precision=precision)
    starts = session.frame_starts
    for chunk_frames in (1, 2, 5, 7, 24):
        chunks = [
            session.select(slice(int(starts[a]), int(starts[min(a + chunk_frames, 24)])))
            for a in range(0, 24, chunk_frames)
        ]
        streamed: list[dict] = []
        result = replay_chunks(chunks, nominal, precision=precision, on_trace=streamed.append)
        assert np.array_equal(result.params.model_vector(), whole.params.model_vector())
        for name in ("x_hi", "x_lo", "u", "d"):  # the whole estimator state, not only the parameters
            assert np.array_equal(getattr(result.state, name), getattr(whole.state, name)), name
        assert result.trace is None  # streamed, not kept
        joined = {c: [v for t in streamed for v in t[c]] for c in TRACE_COLUMNS}
        _assert_same_trace(joined, whole.trace)
        assert (result.frames, result.frames_used, result.rejected_stars) == (
            whole.frames,
            whole.frames_used,
            whole.rejected_stars,
        )


def test_replay_command_streams_a_parquet_session_and_writes_the_in_memory_trace(tmp_path, session, capsys):
    write_session(tmp_path / "s.parquet", session)
    whole = replay_session(read_session(tmp_path / "s.parquet"), load_params(NOMINAL))
    write_trace(tmp_path / "expected.csv", whole.trace)
    code = main(
        ["replay", str(tmp_path / "s.parquet"), "--nominal", NOMINAL, "--out", str(tmp_path / "e.json")]
        + ["--trace", str(tmp_path / "trace.csv")]
    )
    assert code == 0, capsys.readouterr().err
    assert (tmp_path / "trace.csv").read_text() == (tmp_path / "expected.csv").read_text()
    estimate = json.loads((tmp_path / "e.json").read_text())
    assert estimate["focal_length_mm"] == whole.params.focal_length_mm
    assert estimate["frames"] == 24 and estimate["frames_used"] == whole.frames_used


def test_replay_of_a_session_split_over_two_files_equals_the_replay_of_one(tmp_path, session, capsys):
    write_session(tmp_path / "one.csv", session)
    write_session(tmp_path / "night2.csv", session.select(session.frame >= session.frame[0] + 10))
    write_session(tmp_path / "night1.csv", session.select(session.frame < session.frame[0] + 10))
    outs = []
    for k, sources in enumerate(([str(tmp_path / "one.csv")], [str(tmp_path / "night*.csv")])):
        out = tmp_path / f"e{k}.json"
        assert main(["replay", *sources, "--nominal", NOMINAL, "--out", str(out), "--trace", f"{out}.csv"]) == 0
        outs.append((json.loads(out.read_text()), (tmp_path / f"e{k}.json.csv").read_text()))
    capsys.readouterr()
    assert outs[0] == outs[1]


def test_a_failed_replay_leaves_neither_estimate_nor_trace(tmp_path, session, capsys):
    unidentified = session.select(np.arange(len(session)))
    unidentified.star_id[:] = 0
    write_session(tmp_path / "s.parquet", unidentified)
    write_session(tmp_path / "empty.csv", session.select(np.zeros(0, dtype=np.int64)))
    for name, message in (("s.parquet", "no frame had 3 or more"), ("empty.csv", "empty.csv: no frames")):
        code = main(
            ["replay", str(tmp_path / name), "--nominal", NOMINAL, "--out", str(tmp_path / "e.json")]
            + ["--trace", str(tmp_path / "t.csv")]
        )
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1
        assert not (tmp_path / "e.json").exists() and not (tmp_path / "t.csv").exists()
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith("t.csv")] == []  # no temporary left


def test_replay_memory_does_not_grow_with_the_number_of_frames(session):
    nominal = load_params(NOMINAL)
    chunk = session.select(session.frame < session.frame[0] + 6)
    sink_rows = []

    def peak_bytes(n_chunks: int) -> int:
        chunks = (chunk for _ in range(n_chunks))  # made one at a time, as read from a file
        tracemalloc.start()
        replay_chunks(chunks, nominal, on_trace=lambda t: sink_rows.append(len(t["frame"])))
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return peak

    small, large = peak_bytes(5), peak_bytes(45)
    assert sum(sink_rows) == 50 * 6
    # the estimator and one chunk are the same in both runs; a trace kept in memory would add ~0.75 kB per frame
    # (240 more frames: ~180 kB). Allowed: 100 kB, above the swing of uncollected cyclic garbage between two runs
    # (measured: up to 40 kB, not growing with the frames)
    assert large - small < 100_000, (small, large)


def test_read_session_chunks_feeds_replay_chunks_in_order(tmp_path, session):
    write_session(tmp_path / "s.parquet", session)
    result = replay_chunks(read_session_chunks(tmp_path / "s.parquet", 4), load_params(NOMINAL), keep_trace=True)
    assert result.trace["frame"] == [int(f) for f in concatenate_sessions([session]).frame[session.frame_starts[:-1]]]
    with pytest.raises(UserError, match="no frames"):
        replay_chunks(iter([]), load_params(NOMINAL))
