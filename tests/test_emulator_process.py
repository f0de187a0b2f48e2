"""The one launcher of an emulated sensor in its own process (``hostlink.emulator.process.EmulatorProcess``)."""

import pytest

from hostlink.emulator.process import EmulatorProcess, emulate_command
from hostlink.errors import UserError
from hostlink.links import open_link


def test_emulator_is_ready_when_constructed_and_stops_cleanly_on_sigterm():
    with EmulatorProcess("serial", ["--sim-frames", "20"]) as emulator:
        assert emulator.link.startswith("serial:")
        with open_link(emulator.link) as link:  # ready means: the endpoint answers now, with no wait
            assert link.status().frames_processed == 0
        code = emulator.stop()
    assert code == 0  # the emulator's SIGTERM handler ends its serve loop: a clean exit, not a kill


def test_an_emulator_that_cannot_start_is_one_line_naming_the_cause(tmp_path):
    missing = tmp_path / "none.csv"
    with pytest.raises(UserError) as err:
        EmulatorProcess("serial", ["--replay", str(missing)])
    message = str(err.value)
    assert message.startswith("the emulated sensor did not start: ") and "\n" not in message
    assert "none.csv" in message


def test_a_flash_image_is_passed_as_the_flash_option():
    command = emulate_command("can", ["--seed", "3"], flash_path="sensor.flash")
    assert command[3:] == ["emulate", "--transport", "can", "--flash", "sensor.flash", "--seed", "3"]
    assert "--flash" not in emulate_command("can", ["--seed", "3"])
