"""Fixtures shared by the test modules (pytest loads this file first).

The markers: ``slow`` marks the soak, the Monte Carlo runs (many sessions or trials scored against the Cramer-Rao
bound), the whole-mission bench runs and other long end-to-end tests. CI runs everything (``scripts/test.sh``); the
fast lane for working is ``pytest -m "not slow"`` (README).
"""

from __future__ import annotations

import pytest

from hostlink.api import SimConfig, simulate, write_session
from hostlink.sky.simulate import seed004_camera


@pytest.fixture(scope="session")
def replay_file(tmp_path_factory):
    """A short session for an emulated sensor to replay (``hostlink emulate --replay``): seed 004's camera, 50 frames,
    0.01 px noise, 10 % false stars (rows with no identity), written once for every link test."""
    path = tmp_path_factory.mktemp("replay") / "session.csv"
    sim = simulate(SimConfig(camera=seed004_camera(), frames=50, noise_px=0.01, seed=11, false_star_fraction=0.1))
    write_session(path, sim.session)
    return path


@pytest.fixture
def recorded_progress(monkeypatch):
    """The progress bars a command opens, recorded instead of drawn: a list of (what, total, enabled, the advances
    made), one entry per bar (``hostlink.api.progress_bar`` replaced for the test)."""
    import contextlib

    import hostlink.api

    shown: list[tuple[str, int | None, bool, list[int]]] = []

    @contextlib.contextmanager
    def recording_bar(what, total, enabled=True):
        advanced: list[int] = []
        shown.append((what, total, enabled, advanced))
        yield advanced.append

    monkeypatch.setattr(hostlink.api, "progress_bar", recording_bar)
    return shown
