"""A Modbus TCP answer that lost a byte on the way down still carries its MBAP length, which then promises a byte that
will not come: pymodbus waited for it until the whole answer wait had passed. At three times the default fault rates
(scripts/link_faults.py --drop 0.03 --ber 3e-4 --both-directions) most answers are damaged, the wait is backed off
to the device's longest response time (0.2 s) by the lost ones, and a read failed ~50 times in a row (p ~ 0.88 each
for 22 registers) within the link's 10 s patience about once per run (docs/links.md). Now the rest of an answer whose
header has come is waited for only ``_ANSWER_REST_S``. Checked with the real pymodbus client and the emulator behind
a relay that drops one answer byte: the recv after the cut-short answer is given the short timeout (no clock is
read: pymodbus reads the timeout of each recv from ``comm_params.timeout_connect``), and the link goes on."""

from __future__ import annotations

import pytest
from emulator_fixtures import running_emulator
from pymodbus.client import ModbusTcpClient
from register_fakes import DropOneByte

from hostlink.emulator.fault_relay import FaultModel, relay_link
from hostlink.links import open_link
from hostlink.links.modbus_adapter import _ANSWER_REST_S, answer_cut_short

#: A whole answer of 2 registers (transaction 7, unit 1, function 4, 4 bytes) as a device sends it.
_ANSWER = bytes.fromhex("0007 0000 0007 01 04 04 0102 0304".replace(" ", ""))


@pytest.mark.parametrize(
    ("received", "cut_short"),
    [
        (b"", False),
        (_ANSWER, False),
        (_ANSWER[:-1], True),  # a byte lost: the length promises one more
        (_ANSWER[:4], True),  # the header not yet whole
        (_ANSWER + _ANSWER, False),  # a late answer to an earlier request, then this one
        (_ANSWER + _ANSWER[:-1], True),
        (_ANSWER[:1] + _ANSWER[2:], True),  # the transaction id's low byte lost: the length reads 0x0701
        (bytes.fromhex("00070100000701040401020304"), True),  # a protocol id other than 0: pymodbus never frames it
    ],
)
def test_answer_cut_short(received, cut_short):
    assert answer_cut_short(received) is cut_short


def test_a_cut_short_answer_waits_briefly_for_its_rest(monkeypatch):
    timeouts: list[tuple[float, int]] = []  # (the timeout of each recv, the bytes it returned)
    real_recv = ModbusTcpClient.recv

    def recorded_recv(self, size):  # noqa: ANN001, ANN202 - pymodbus's signature
        timeout_s = self.comm_params.timeout_connect
        data = real_recv(self, size)
        timeouts.append((timeout_s, len(data)))
        return data

    monkeypatch.setattr(ModbusTcpClient, "recv", recorded_recv)
    with running_emulator("modbus", "--sim-frames", "5", "--no-estimator") as info:
        down = DropOneByte(
            at=20
        )  # the answer stream's byte 20, in the first answer's registers: its header arrives whole
        relayed, relay = relay_link(info["link"], down, FaultModel())
        try:
            with open_link(relayed, timeout_s=10.0) as link:
                telemetry = link.status()
                assert down.bytes_dropped == 1
                assert link.stats.corrupt_frames >= 1  # the cut-short answer failed its try
                for _ in range(3):  # the link goes on
                    assert link.status().active_generation == telemetry.active_generation
        finally:
            relay.close()
    first_wait_s, got = timeouts[0]
    assert got > 8  # the first answer's header came, without the dropped byte
    assert first_wait_s > _ANSWER_REST_S  # the whole answer wait until then
    assert timeouts[1] == (_ANSWER_REST_S, 0)  # the rest: a short wait, and nothing came
    assert timeouts[2][0] > _ANSWER_REST_S  # the next try has the whole wait again
