"""``hostlink simulate`` streams to disk chunk by chunk (issue 31): the files written chunk by chunk are the files of
the same simulation collected in memory, byte for byte, for a session of several chunks with misidentified and false
stars. The memory itself is measured in benchmarks/bench_simulate_memory.py (docs/commands.md gives the figures)."""

from dataclasses import replace

import numpy as np
import pytest

from hostlink.files.session import read_session, write_session
from hostlink.files.truth import read_truth, write_truth
from hostlink.sky import simulate as sim


def test_streamed_files_equal_the_simulation_in_memory(tmp_path, monkeypatch):
    """Chunks of 300 frames (so 1000 frames are four chunks): the session and truth written chunk by chunk equal those
    of simulate() collected and written whole; the truth's row lists point at the right rows of the whole file."""
    monkeypatch.setattr(sim, "_CHUNK_FRAMES", 300)
    cfg = replace(sim.seed004_config(frames=1000, seed=9), misid_fraction=0.05, false_star_fraction=0.1)
    frames, rows = sim.write_simulation(cfg, tmp_path / "s.csv", tmp_path / "s.truth.json")
    whole = sim.simulate(cfg)
    write_session(tmp_path / "w.csv", whole.session)
    write_truth(tmp_path / "w.truth.json", whole.truth)
    assert (tmp_path / "s.csv").read_bytes() == (tmp_path / "w.csv").read_bytes()
    assert (tmp_path / "s.truth.json").read_bytes() == (tmp_path / "w.truth.json").read_bytes()
    assert frames == 1000 and rows == len(whole.session)
    truth = read_truth(tmp_path / "s.truth.json")
    session = read_session(tmp_path / "s.csv")
    assert truth["attitude"].shape == (1000, 3, 3) and truth["misidentified_rows"].size > 0
    assert np.all(session.star_id[truth["false_rows"]] == 0)
    assert np.all(session.star_id[truth["misidentified_rows"]] != truth["misidentified_true_star_id"])
    assert np.all(np.bincount(session.frame[session.star_id != 0], minlength=1000) >= 1)


def test_a_failed_simulation_leaves_no_files(tmp_path, monkeypatch):
    """A simulation that fails part way (here: the second chunk's sky cannot be built) leaves no file at all."""
    monkeypatch.setattr(sim, "_CHUNK_FRAMES", 300)
    real = sim._chunk_sky

    def failing(cfg, jd1, jd2, a, b):
        if a > 0:
            raise sim.UserError("stop")
        return real(cfg, jd1, jd2, a, b)

    monkeypatch.setattr(sim, "_chunk_sky", failing)
    with pytest.raises(sim.UserError, match="stop"):
        sim.write_simulation(sim.seed004_config(frames=1000, seed=9), tmp_path / "s.csv", tmp_path / "s.truth.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # not even s.csv.partial
