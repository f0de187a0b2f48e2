"""Test helpers for emulated sensors (shared by the serial, CAN and Modbus link tests).

``running_emulator(transport, *args)`` starts ``hostlink emulate --transport T ARGS`` as a separate process (as a
user would), reads the JSON line it prints first, yields it (with ``process`` added) and stops the process on exit.
``hostlink(*args)`` runs the CLI in a subprocess and returns the CompletedProcess (text mode).
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import subprocess
import sys
from collections.abc import Iterator

#: The emulator builds its source (simulator or replay) before printing: allow for a slow, shared machine.
STARTUP_TIMEOUT_S = 60.0
_CLI = [sys.executable, "-m", "hostlink.cli"]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("HOSTLINK_DEBUG", None)
    return env


@contextlib.contextmanager
def running_emulator(transport: str, *args: str, startup_timeout_s: float = STARTUP_TIMEOUT_S) -> Iterator[dict]:
    proc = subprocess.Popen(
        [*_CLI, "emulate", "--transport", transport, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(startup_timeout_s):
            raise RuntimeError(f"emulator ({transport}) printed nothing within {startup_timeout_s} s")
        line = proc.stdout.readline()
        if not line:
            raise RuntimeError(f"emulator ({transport}) exited: {proc.wait(5)} {proc.stderr.read()}")
        info = json.loads(line)
        info["process"] = proc
        yield info
    finally:
        stop_process(proc)


def stop_process(proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
    """SIGTERM, then SIGKILL if it does not exit; returns the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()
    return proc.returncode


def hostlink(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """Run ``hostlink ARGS`` in a subprocess."""
    return subprocess.run([*_CLI, *args], capture_output=True, text=True, timeout=timeout_s, env=_env())
