"""``can:`` links take python-can's own configuration as python-can does (issue 31): ``can:config`` and
``can:config:CONTEXT`` read the interface, channel and bit rate from the environment (``CAN_INTERFACE``,
``CAN_CHANNEL``, ``CAN_BITRATE``) or ``~/.canrc`` through ``can.util.load_config``; an explicit link string still
wins; ``hostlink.api.open_link`` runs on a ``can.BusABC`` the caller opened and leaves it open. Checked against the
CAN emulator process (an SLCAN adapter over TCP) with the real python-can."""

import can
import pytest
from emulator_fixtures import hostlink, running_emulator

from hostlink import api
from hostlink.errors import UserError
from hostlink.links.can_link import CanTarget, bus_config, parse_target


@pytest.fixture(scope="module")
def sensor():
    with running_emulator("can", "--sim-frames", "5", "--no-estimator", "--bitrate", "500000") as info:
        yield info


def channel_of(link: str) -> str:
    """``can:slcan:socket://127.0.0.1:PORT@500000`` -> ``socket://127.0.0.1:PORT``."""
    return link.split(":", 2)[2].rsplit("@", 1)[0]


def test_config_targets_parse():
    assert parse_target("config") == CanTarget("", "", 500_000)
    t = parse_target("config:bench@250000,fd=false")
    assert t == CanTarget("", "", 250_000, {"fd": False}, "bench") and t.explicit_bitrate
    assert not parse_target("virtual:test").explicit_bitrate and parse_target("virtual:test@125000").explicit_bitrate
    with pytest.raises(UserError):
        parse_target("config@fast")


def test_python_can_environment_fills_what_the_string_leaves_out(monkeypatch):
    """Resolved by can.util.load_config: the environment's bit rate applies when the string gives none, the string's
    wins when it gives one, and our default 500 kbit/s only where neither does."""
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "bench0")
    monkeypatch.setenv("CAN_BITRATE", "250000")
    monkeypatch.setenv("HOME", "/nonexistent")  # no ~/.canrc of the machine's user
    resolved = bus_config(parse_target("config"))
    assert {k: resolved[k] for k in ("interface", "channel", "bitrate")} == {
        "interface": "virtual",
        "channel": "bench0",
        "bitrate": 250000,
    }
    assert bus_config(parse_target("virtual:other"))["bitrate"] == 250000
    assert bus_config(parse_target("virtual:other@125000"))["bitrate"] == 125000
    monkeypatch.delenv("CAN_BITRATE")
    assert bus_config(parse_target("virtual:other"))["bitrate"] == 500000
    monkeypatch.delenv("CAN_INTERFACE")
    monkeypatch.delenv("CAN_CHANNEL")
    with pytest.raises(UserError, match="names no usable interface"):
        bus_config(parse_target("config"))


def test_can_config_link_reads_the_environment_as_python_can_does(sensor, monkeypatch):
    monkeypatch.setenv("CAN_INTERFACE", "slcan")
    monkeypatch.setenv("CAN_CHANNEL", channel_of(sensor["link"]))
    monkeypatch.setenv("CAN_BITRATE", "500000")
    run = hostlink("params", "--link", "can:config")
    assert run.returncode == 0, run.stderr
    assert run.stdout == hostlink("params", "--link", sensor["link"]).stdout


def test_can_config_context_reads_a_section_of_canrc(sensor, tmp_path, monkeypatch):
    (tmp_path / ".canrc").write_text(
        f"[default]\ninterface = virtual\nchannel = unused\n\n"
        f"[sensor]\ninterface = slcan\nchannel = {channel_of(sensor['link'])}\nbitrate = 500000\n"
    )
    monkeypatch.setenv("HOME", str(tmp_path))
    for key in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(key, raising=False)
    run = hostlink("params", "--link", "can:config:sensor")
    assert run.returncode == 0, run.stderr
    assert run.stdout == hostlink("params", "--link", sensor["link"]).stdout


def test_open_link_runs_on_a_bus_the_user_opened_and_leaves_it_open(sensor):
    bus = can.Bus(interface="slcan", channel=channel_of(sensor["link"]), bitrate=500000, sleep_after_open=0)
    try:
        with api.open_link(bus) as link:
            active = api.read_active_params(link)
        assert active.generation >= 1 and active.params.focal_length_mm > 0
        with api.open_link(bus) as link:  # the bus outlived the first link: it is the user's to shut down
            assert api.read_active_params(link).generation == active.generation
    finally:
        bus.shutdown()
    with pytest.raises(UserError, match="python-can bus"):
        api.open_link(42)
