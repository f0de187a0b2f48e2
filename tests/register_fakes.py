"""Fakes of a Modbus link's line for in-process and relay tests (shared by the Modbus link tests).

``ImageRegisterClient(image)``: a RegisterClient straight on the emulator's register image (no line: reset, the
answer timeout and close do nothing); tests subclass it to script a line's faults or timing.
``DropOneByte(at)``: a relay fault model that drops the byte ``at`` of its stream and nothing else.
"""

from __future__ import annotations

from hostlink.emulator.fault_relay import FaultModel
from hostlink.emulator.modbus_endpoint import RegisterSensor


class ImageRegisterClient:
    """A RegisterClient talking straight to the emulator's register image."""

    def __init__(self, image: RegisterSensor) -> None:
        self.image = image

    def read(self, table: str, address: int, count: int) -> list[int]:
        return self.image.on_read(table, address, count)

    def write(self, address: int, values: list[int]) -> None:
        self.image.on_write(address, values)

    def reset(self) -> None:
        pass

    def set_answer_timeout(self, timeout_s: float) -> None:
        pass

    def close(self) -> None:
        pass


class DropOneByte(FaultModel):
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
