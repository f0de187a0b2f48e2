"""A Modbus request that loses one byte on the way up leaves the device's framer waiting for it (Modbus TCP: the
MBAP length; RTU: the frame), so the next request on that connection completes the broken one and is lost with it.
The link opens a fresh connection after every failed exchange: one lost request byte costs one try, not two (with
the old rule, a reset after two failures in a row, the second try was doomed and faults host -> sensor ended 1 of
2 runs of scripts/link_faults.py --both-directions in a LinkError)."""

from __future__ import annotations

import pytest
from emulator_fixtures import running_emulator

from hostlink.emulator.fault_relay import FaultModel, relay_link
from hostlink.links import open_link


class _DropOneByte(FaultModel):
    """A line that drops the byte at ``at`` (counted from the first byte it carries) and nothing else."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at

    def apply(self, data: bytes) -> bytes:
        start = self.bytes_in
        self.bytes_in += len(data)
        k = self.at - start
        if 0 <= k < len(data):
            self.bytes_dropped += 1
            return data[:k] + data[k + 1 :]
        return data


@pytest.mark.parametrize("rtu", [False, True], ids=["modbus-tcp", "modbus-rtu"])
def test_a_request_that_lost_a_byte_costs_one_try(rtu):
    with running_emulator("modbus", "--sim-frames", "5", "--no-estimator") as info:
        up = _DropOneByte(at=5)  # in the first request: the low byte of its MBAP length (RTU: its count)
        relayed, relay = relay_link(info["link_rtu"] if rtu else info["link"], FaultModel(), up)
        try:
            with open_link(relayed, timeout_s=2.0) as link:
                telemetry = link.status()
                assert up.bytes_dropped == 1
                assert link.stats.corrupt_frames == 1  # the broken request, and only it, failed
                assert telemetry.active_generation >= 1
                for _ in range(3):  # the link goes on clean
                    link.status()
                assert link.stats.corrupt_frames == 1
        finally:
            relay.close()
