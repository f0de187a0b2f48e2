"""Test helpers for emulated sensors (shared by the serial, CAN and Modbus link tests).

``running_emulator(transport, *args)`` starts ``hostlink emulate --transport T ARGS`` as a separate process (as a
user would) through the one launcher, ``hostlink.emulator.process.EmulatorProcess``, yields the JSON line it prints
first (with ``process`` added) and stops the process on exit.
``hostlink(*args)`` runs the CLI in a subprocess and returns the CompletedProcess (text mode).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

from hostlink.emulator.process import EmulatorProcess

#: The emulator builds its source (simulator or replay) before printing: allow for a slow, shared machine.
STARTUP_TIMEOUT_S = 60.0
_CLI = [sys.executable, "-m", "hostlink.cli"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("HOSTLINK_DEBUG", None)
    return env


@contextlib.contextmanager
def running_emulator(transport: str, *args: str, startup_timeout_s: float = STARTUP_TIMEOUT_S) -> Iterator[dict]:
    """The emulator's ready line (``link`` and the transport's details) with ``process`` (its Popen) added."""
    with EmulatorProcess(transport, args, startup_timeout_s=startup_timeout_s, env=_env()) as emulator:
        yield emulator.info | {"process": emulator.process}


def hostlink(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """Run ``hostlink ARGS`` in a subprocess."""
    return subprocess.run([*_CLI, *args], capture_output=True, text=True, timeout=timeout_s, env=_env())
