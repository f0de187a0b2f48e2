"""A command whose stdout reader has gone (`hostlink costs | head -1`) ends quietly, as a shell tool does."""

import os
import subprocess
import sys


def test_a_closed_stdout_ends_the_command_quietly_with_the_sigpipe_status():
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the command writes anything: every write fails with EPIPE
    try:
        run = subprocess.run(
            [sys.executable, "-m", "hostlink.cli", "costs", "--stars", "8"],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
        )
    finally:
        os.close(write_end)
    assert run.returncode == 128 + 13, run.stderr
    assert run.stderr == ""
