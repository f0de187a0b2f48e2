"""``hostlink emulate`` as a separate process: THE launcher of an emulated sensor (the bench and the tests use it).

The emulator prints one JSON line on stdout once its endpoint is open (``{"link": ..., "transport": ...}``, see
``hostlink/commands/emulate.py``). That line is the readiness event: :class:`EmulatorProcess` waits for it with a
deadline (never a fixed sleep), keeps it as :attr:`EmulatorProcess.info` and the link string as
:attr:`EmulatorProcess.link`, and stops the process with SIGTERM (then SIGKILL) on :meth:`EmulatorProcess.stop`.

The emulator's stderr goes to a temporary file, not a pipe: a long run cannot fill a pipe nobody reads and stall the
sensor, and the last line is at hand for the one-line error when it fails to start.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from hostlink.errors import UserError

#: The emulator builds its frame source (simulator or replay file) before it prints: allow for a slow, shared machine.
STARTUP_TIMEOUT_S = 120.0
#: How long SIGTERM has to end the process before SIGKILL (the endpoints poll their stop event every few ms).
STOP_TIMEOUT_S = 10.0


def emulate_command(transport: str, args: Sequence[str] = (), flash_path: str | Path | None = None) -> list[str]:
    """The command line of ``hostlink emulate --transport TRANSPORT [--flash FILE] ARGS`` in this interpreter."""
    flash = ["--flash", str(flash_path)] if flash_path is not None else []
    return [sys.executable, "-m", "hostlink.cli", "emulate", "--transport", transport, *flash, *map(str, args)]


class EmulatorProcess:
    """An emulated sensor in its own process, ready when constructed; a context manager that stops it on exit.

    ``transport``: ``serial``, ``can`` or ``modbus``; ``args``: further ``hostlink emulate`` options; ``flash_path``:
    the sensor's flash image (``--flash FILE``); ``env``: the child's environment (default: this one).
    Raises :class:`~hostlink.errors.UserError` (one line) when the emulator exits or stays silent past
    ``startup_timeout_s`` [s], or prints something other than its JSON line."""

    def __init__(
        self,
        transport: str,
        args: Sequence[str] = (),
        *,
        flash_path: str | Path | None = None,
        startup_timeout_s: float = STARTUP_TIMEOUT_S,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.transport = transport
        self._stderr = tempfile.TemporaryFile(mode="w+b")
        self.process = subprocess.Popen(
            emulate_command(transport, args, flash_path),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            env=dict(env) if env is not None else None,
        )
        try:
            line = _first_line(self.process, startup_timeout_s)
            if not line:
                self.stop()  # reaped, so that its stderr is complete
                why = "it exited" if line is not None else f"no link within {startup_timeout_s:g} s"
                raise UserError(f"the emulated sensor did not start: {self._stderr_tail() or why}")
            self.info: dict = _parse_ready_line(line)
            self.link: str = str(self.info["link"])
        except BaseException:
            self.stop()
            self._stderr.close()
            raise

    def _stderr_tail(self) -> str:
        self._stderr.seek(0)
        lines = self._stderr.read().decode("utf-8", "replace").strip().splitlines()
        return lines[-1] if lines else ""

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int:
        """SIGTERM, then SIGKILL if the process has not exited within ``timeout_s`` [s]; returns the exit code."""
        proc = self.process
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout_s)
        if proc.stdout is not None:
            proc.stdout.close()
        return int(proc.returncode)

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self._stderr.close()


def _first_line(proc: subprocess.Popen, timeout_s: float) -> bytes | None:
    """The first stdout line of ``proc``, read as it arrives; b"" if the process closed its stdout (exited) first,
    None if ``timeout_s`` [s] passed first."""
    fd = proc.stdout.fileno()
    deadline = time.monotonic() + timeout_s
    buf = b""
    with selectors.DefaultSelector() as sel:
        sel.register(fd, selectors.EVENT_READ)
        while b"\n" not in buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not sel.select(remaining):
                return None
            chunk = os.read(fd, 4096)
            if not chunk:  # end of file: the process exited
                return b""
            buf += chunk
    return buf.split(b"\n", 1)[0]


def _parse_ready_line(line: bytes) -> dict:
    """The emulator's JSON readiness line as a dict with a ``link`` key, or a one-line UserError."""
    try:
        info = json.loads(line)
        str(info["link"])
    except (ValueError, KeyError, TypeError):
        text = line.decode(errors="replace")
        raise UserError(f"the emulated sensor printed an unexpected first line: {text!r}") from None
    return info
