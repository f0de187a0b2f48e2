"""The emulated sensor's NOR flash as a file (``hostlink emulate --flash FILE``): the parameter banks and the
generation and staging-session counters survive a restart, and a kill of the emulator at any moment is a power cut.

The record layout, the NOR rules (erase to 0xFF, programming only clears bits, ``WRITE_BYTES`` units) and start-up
recovery are the sensor's own (``onboard.banks``); this module only mirrors every change into the file, one write
unit per ``os.pwrite`` in address order, so a process killed during an erase or a program leaves the file exactly as
a power cut after that many units leaves the flash. No fsync: the power cut modelled is the sensor's (the process
dies; the host's page cache keeps what was written), not the host machine's.

The file is locked (``fcntl.flock``) while an emulator uses it: two sensors never share one flash. A new image is
created whole (blank, through :mod:`hostlink.files.atomic`); an existing one is opened with ``O_NOFOLLOW``: a
symbolic link at the flash path is refused, never written through.

Test hook: ``power_cut_after_units`` = N makes the process SIGKILL itself right after the N-th write unit it writes
(``hostlink emulate --power-cut-after N``): a power cut placed at an exact unit of an erase or program, whatever the
speed of the machine (``scripts/flash_power_cuts.py`` also kills from outside at random times).
"""

from __future__ import annotations

import fcntl
import os
import signal
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.atomic import write_bytes
from onboard.banks import ERASED_BYTE, FLASH_BYTES, SECTOR_BYTES, WRITE_BYTES, nor_erase, nor_program


class FileFlash:
    """A flash image in a file: ``read`` from memory, ``erase`` / ``program`` applied to memory and written through
    to the file unit by unit (the duck type of ``onboard.banks.FlashDevice``)."""

    def __init__(self, path: str | Path, power_cut_after_units: int | None = None) -> None:
        self.path = Path(path)
        self.power_cut_after_units = power_cut_after_units
        self.units_written = 0
        if not os.path.lexists(self.path):  # a new image: blank flash, created whole
            try:
                write_bytes(self.path, bytes([ERASED_BYTE]) * FLASH_BYTES)
            except UserError as exc:
                raise UserError(f"--flash {exc}") from None
        try:
            self._fd = os.open(self.path, os.O_RDWR | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        except OSError as exc:
            if os.path.islink(self.path):
                raise UserError(
                    f"--flash {self.path}: a symbolic link (refused: the flash is written in place)"
                ) from None
            raise UserError(f"--flash {self.path}: cannot open ({exc.strerror})") from None
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            raise UserError(f"--flash {self.path}: in use by another emulated sensor") from None
        size = os.fstat(self._fd).st_size
        if size == 0:  # an empty file: blank flash
            self.image = np.full(FLASH_BYTES, ERASED_BYTE, dtype=np.uint8)
            os.pwrite(self._fd, self.image.tobytes(), 0)
        elif size == FLASH_BYTES:
            self.image = np.frombuffer(os.pread(self._fd, FLASH_BYTES, 0), dtype=np.uint8).copy()
        else:
            os.close(self._fd)
            raise UserError(f"--flash {self.path}: {size} bytes is not a flash image ({FLASH_BYTES} bytes)")

    def read(self, address: int, n: int) -> bytes:
        return self.image[address : address + n].tobytes()

    def _write_through(self, start: int, stop: int) -> None:
        for unit in range(start, stop, WRITE_BYTES):
            if self.units_written == self.power_cut_after_units:
                os.kill(os.getpid(), signal.SIGKILL)  # the test hook's power cut: nothing after this unit
            os.pwrite(self._fd, self.image[unit : unit + WRITE_BYTES].tobytes(), unit)
            self.units_written += 1

    def erase(self, sector: int) -> None:
        nor_erase(self.image, sector)
        self._write_through(sector * SECTOR_BYTES, (sector + 1) * SECTOR_BYTES)

    def program(self, address: int, data: bytes) -> None:
        nor_program(self.image, address, np.frombuffer(bytes(data), dtype=np.uint8))
        self._write_through(address, address + len(data))

    def close(self) -> None:
        """Release the file (and its lock). Idempotent."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
