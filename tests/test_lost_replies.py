"""Commands that must not run twice, on a message link whose replies get lost (issue 33): STAGE_BEGIN is sent again
as a new command (only the reply to the latest counts: its nonce is the live one), COMMIT once more only when the
active set shows it did not run. In process (LoopbackLink), deterministic: which reply or command is lost is chosen."""

import pytest

from hostlink.emulator.loopback import LoopbackLink
from hostlink.emulator.sensor import EmulatedSensor
from hostlink.links.operations import safe_upload
from onboard import banks
from onboard.firmware import Firmware
from onboard.params import CameraParams
from protocol import messages as m

NOMINAL = CameraParams(
    focal_length_mm=70.0, pixel_pitch_um=12.0, principal_point_px=(511.5, 511.5), image_size_px=(1024, 1024)
)
NEW = CameraParams(
    focal_length_mm=70.3, pixel_pitch_um=12.0, principal_point_px=(512.0, 510.5), image_size_px=(1024, 1024)
)


class _LossyLink(LoopbackLink):
    """Loses the first reply to (``lose="reply"``) or the first copy of (``lose="command"``) each command type in
    ``types``; counts what the sensor ran."""

    def __init__(self, sensor: EmulatedSensor, types: tuple[type, ...], lose: str) -> None:
        super().__init__(sensor, timeout_s=0.3)
        self.types, self.lose = types, lose
        self.lost: set[type] = set()
        self.ran: list[type] = []

    def _send(self, msg: m.Message) -> None:
        first = isinstance(msg, self.types) and type(msg) not in self.lost
        if first:
            self.lost.add(type(msg))
        if first and self.lose == "command":
            return  # lost on the way: the sensor never sees it
        self.ran.append(type(msg))
        n = len(self._inbox)
        super()._send(msg)
        if first and self.lose == "reply":
            while len(self._inbox) > n:
                self._inbox.pop()  # the sensor ran it; its reply is lost


def _sensor() -> EmulatedSensor:
    return EmulatedSensor(Firmware(banks.factory_store(NOMINAL), None), iter(()))


@pytest.mark.parametrize("lose", ["reply", "command"])
@pytest.mark.parametrize("kind", [m.StageBegin, m.Commit])
def test_an_upload_completes_once_when_a_stage_begin_or_commit_is_lost(kind, lose):
    sensor = _sensor()
    link = _LossyLink(sensor, (kind,), lose)
    before = link.read_active().generation
    safe_upload(link, NEW, host_check=False)
    after = link.read_active()
    assert after.generation == before + 1  # committed exactly once
    assert link.ran.count(m.Commit) == 1  # the sensor ran one COMMIT (a lost one never reached it)
    if kind is m.StageBegin:
        assert link.ran.count(m.StageBegin) == (2 if lose == "reply" else 1)  # sent again as a new command


def test_a_commit_whose_reply_is_lost_is_not_sent_again_once_the_active_set_shows_it():
    sensor = _sensor()
    link = _LossyLink(sensor, (m.Commit,), "reply")
    safe_upload(link, NEW, host_check=False)
    assert link.ran.count(m.Commit) == 1 and link.ran.count(m.ReadActive) >= 2  # asked, not committed twice
