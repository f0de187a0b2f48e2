"""Every option of every quick command, one at a time, set to values that break programs (issue 15: "no internal
error on any CLI input"): the command must succeed or refuse in one line with a non-zero exit code, never exit 1
(an internal error), raise, print a traceback or hang.

    python scripts/cli_sweep.py                          # every command below, every option, every odd value
    python scripts/cli_sweep.py --commands stream,upload

Each case is a valid baseline command line (a 3-frame simulated session, the shipped parameter files, a serial port
that does not exist for the link commands) with ONE option appended again with an odd value (argparse keeps the last
occurrence), run in this process through ``hostlink.cli.main`` with stdout and stderr captured and an interval timer
as the hang limit (``--hang-s``). Commands that serve or run for minutes with valid input (``emulate``, ``bench``,
``example``) are left out: their bad options are cases of tests/test_cli_bad_options.py. One JSON line per failure,
then a summary line; exit code 1 on any failure. The short version runs in CI as tests/test_cli_sweep.py.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import signal
import sys
import tempfile
from pathlib import Path

from hostlink.cli import build_parser, main

#: Values that break programs: empty, non-finite, negative, zero, out of range, not a number, a list, too long for
#: Python to convert, a date that does not exist.
ODD_VALUES = ("", "nan", "-1", "0", "1e999", "abc", "-inf", "1,2", "9" * 5000, "-0.5", "2026-13-40", "1,2,3,4")
#: A port that cannot exist: the link commands refuse at the link, after their options were read.
NO_PORT = "serial:/nonexistent/hostlink-sweep@9600"


def baselines(d: Path, session: Path) -> dict[str, list[str]]:
    """A valid command line per command (``d``: a scratch folder; ``session``: a valid session file)."""
    s = str(session)
    return {
        "simulate": ["--camera", "builtin:seed004_camera", "--frames", "2", "--out", f"{d}/o.csv"],
        "replay": ["--nominal", "builtin:seed004_nominal", "--out", f"{d}/r.json", s],
        "attitude": ["--params", "builtin:seed004_camera", "--out", f"{d}/a.csv", s],
        "identify": ["--nominal", "builtin:seed004_nominal", "--out", f"{d}/i.csv", s],
        "calibrate": ["--nominal", "builtin:seed004_nominal", "--out", f"{d}/c.json", s],
        "vectors": [f"{d}/v"],
        "costs": [],
        "export-c": [f"{d}/c"],
        "stream": ["--link", NO_PORT, "--frames", "1", "--out", f"{d}/st.csv"],
        "monitor": ["--link", NO_PORT],
        "params": ["--link", NO_PORT],
        "accept": ["--link", NO_PORT],
        "upload": ["--link", NO_PORT, "builtin:seed004_camera"],
        "import-can": ["--out", f"{d}/ic.csv", s],
        "centroid": ["--out", f"{d}/ce.csv", s],
    }


def cases(command: str, baseline: list[str]) -> list[list[str]]:
    """The command line of every (option, odd value) pair of ``command``."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    out = []
    for action in sub.choices[command]._actions:  # noqa: SLF001 - argparse has no public list of options
        if not action.option_strings or action.nargs == 0:
            continue  # positionals (in the baseline) and flags (no value to get wrong)
        out += [[command, *baseline, action.option_strings[-1], value] for value in ODD_VALUES]
    return out


class _Hang(BaseException):
    """Raised by the interval timer in a case that ran past the hang limit (no ``except Exception`` swallows it)."""


def _on_alarm(_signum, _frame) -> None:  # the signal handler signature
    raise _Hang


def judge(argv: list[str], hang_s: float) -> str | None:
    """Run one command line; None if it succeeded or refused in one line, else what went wrong."""
    err, out = io.StringIO(), io.StringIO()
    signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, hang_s)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse refuses a wrong type or choice by exiting 2
                code = exc.code
    except _Hang:
        return f"no answer within {hang_s:g} s"
    except BaseException as exc:  # noqa: BLE001 - anything escaping main is the failure this run looks for
        return f"raised {type(exc).__name__}: {exc}"[:300]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    text = err.getvalue()
    lines = text.strip().splitlines()
    if code == 1 or "Traceback" in text:
        return f"exit {code}: {text.strip()[-300:]}"
    if code not in (0, None) and len(lines) != 1:
        return f"exit {code} with {len(lines)} lines on stderr: {text.strip()[-300:]}"
    return None


def sweep(commands: list[str], hang_s: float = 120.0, on_failure=None) -> tuple[int, list[dict]]:  # noqa: ANN001
    """Run every case of ``commands``; returns (cases run, failures as dicts)."""
    failures: list[dict] = []
    n = 0
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        session = d / "s.csv"
        with contextlib.redirect_stdout(io.StringIO()):
            made = main(["simulate", "--camera", "builtin:seed004_camera", "--frames", "3", "--out", str(session)])
        if made != 0:
            raise RuntimeError("could not simulate the baseline session")
        base = baselines(d, session)
        cwd = os.getcwd()
        os.chdir(d)  # a relative odd path lands in the scratch folder
        try:
            for command in commands:
                for argv in cases(command, base[command]):
                    n += 1
                    problem = judge(argv, hang_s)
                    if problem is not None:
                        failure = {"argv": [a if len(a) < 60 else a[:20] + f"...({len(a)} chars)" for a in argv]}
                        failures.append({**failure, "problem": problem})
                        if on_failure is not None:
                            on_failure(failures[-1])
        finally:
            os.chdir(cwd)
    return n, failures


def main_sweep(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    known = list(baselines(Path("."), Path("s.csv")))
    parser.add_argument("--commands", default=",".join(known), help=f"comma-separated, of: {', '.join(known)}")
    parser.add_argument("--hang-s", type=float, default=120.0, help="a case taking longer is a hang (default 120 s)")
    args = parser.parse_args(argv)
    commands = args.commands.split(",")
    for c in commands:
        if c not in known:
            parser.error(f"unknown command {c!r}")
    n, failures = sweep(commands, args.hang_s, on_failure=lambda f: print(json.dumps(f), flush=True))
    print(json.dumps({"commands": len(commands), "cases": n, "failures": len(failures)}), flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main_sweep())
