"""``hostlink emulate --replay SESSION`` refuses, in one line before it serves, a session the sensor could not send:
a centroid off the nominal camera's detector (1e308 px made the emulator die with an internal EncodeError at the
first frame streamed), a magnitude beyond the wire's int16 millimagnitudes, a frame counter beyond uint32."""

from __future__ import annotations

import pytest

from hostlink.cli import main
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate


@pytest.fixture(scope="module")
def session():
    return simulate(seed004_config(frames=3, seed=2)).session


def _refused(session, tmp_path, capsys, column: str, value) -> str:
    s = session
    values = getattr(s, column).copy()
    values[4] = value
    path = tmp_path / "s.csv"
    old = getattr(s, column)
    setattr(s, column, values)
    try:
        write_session(path, s)
    finally:
        setattr(s, column, old)
    code = main(["emulate", "--transport", "serial", "--replay", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "internal error" not in err, err
    assert len(err) < 300  # a number of 300 digits is not printed whole
    return err


@pytest.mark.parametrize("value", [1e308, -1e308, 1e7])
def test_a_centroid_off_the_detector_is_refused(session, tmp_path, capsys, value):
    assert "off the 1024 x 1024 px detector" in _refused(session, tmp_path, capsys, "x_px", value)


@pytest.mark.parametrize("value", [1e308, -40.0, 33.0])
def test_a_magnitude_beyond_the_wire_is_refused(session, tmp_path, capsys, value):
    assert "line 6: mag" in _refused(session, tmp_path, capsys, "mag", value)


def test_a_frame_counter_beyond_uint32_is_refused(session, tmp_path, capsys):
    values = session.frame.copy()
    values[:] = 2**32 + values  # every row of a frame keeps its frame
    old = session.frame
    session.frame = values
    try:
        path = tmp_path / "s.csv"
        write_session(path, session)
    finally:
        session.frame = old
    code = main(["emulate", "--transport", "serial", "--replay", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "frame" in err and len(err.strip().splitlines()) == 1
