"""The ``hostlink`` console script: one sub-command per module in ``hostlink.commands``.

Each command module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``, and imports its
heavy dependencies inside ``run`` so that ``hostlink --help`` stays fast. Every failure a user can cause is a
:class:`hostlink.errors.UserError`, printed as one line with a non-zero exit code; anything else is reported as an
internal error in one line too (``HOSTLINK_DEBUG=1`` shows the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
import warnings

from hostlink.errors import DISTRIBUTION as _DISTRIBUTION
from hostlink.errors import UserError

#: Sub-commands in the order ``--help`` lists them (module ``hostlink.commands.<name>``).
COMMANDS: tuple[str, ...] = (
    "bench",
    "simulate",
    "centroid",
    "identify",
    "calibrate",
    "replay",
    "attitude",
    "emulate",
    "stream",
    "upload",
    "params",
    "monitor",
    "accept",
    "example",
    "import-can",
    "export-c",
    "export-ground",
    "vectors",
    "costs",
)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # A value starting with '-' and a digit is a value, not an option (as Python 3.13's argparse reads it):
        # `--site -33.9,-70.7,2400` (south, west) and `--weather -5,750` (frost) are docs/interfaces.md syntax.
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str) -> None:  # one line, not usage + message
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


#: The distribution that installs the ``hostlink`` console script (pyproject.toml ``[project] name``).
DISTRIBUTION = _DISTRIBUTION


def package_version() -> str:
    """The installed distribution's version (``importlib.metadata``); ``unknown`` when run from an uninstalled tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown (not installed)"


#: Every help text's last line: the docs/<page>.md pages a help text cites are installed with the package.
DOCS_NOTE = "docs/<page>.md pages are installed with the package: hostlink --docs prints where"


class _DocsAction(argparse.Action):
    """``hostlink --docs``: print the documentation folder and its pages (:mod:`hostlink.docs`), then exit 0."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None) -> None:  # noqa: A002
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, _namespace, _values, _option_string=None) -> None:
        from hostlink.docs import docs_listing

        try:
            print(docs_listing(), flush=True)
        except BrokenPipeError:  # `hostlink --docs | head -1`: quiet, as a shell tool killed by SIGPIPE
            _stdout_closed()
            parser.exit(128 + 13)
        parser.exit(0)


class _VersionAction(argparse.Action):
    """``hostlink --version``: print the version, then exit 0. Looked up only when asked: ``importlib.metadata`` is
    slow enough to notice (docs/realsky.md, "Figures behind the speed choices"), and every command paid it at its
    start when the parser was built with the version in it."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None) -> None:  # noqa: A002
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, _namespace, _values, _option_string=None) -> None:
        print(f"{parser.prog} {package_version()}", flush=True)
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="hostlink",
        description="Star-sensor companion: simulate, calibrate, replay the onboard estimator, and talk to "
        "sensors (real or emulated) over serial, CAN or Modbus.",
    )
    parser.add_argument("--version", action=_VersionAction, help="show program's version number and exit")
    parser.add_argument("--docs", action=_DocsAction, help=f"print where the documentation is ({DOCS_NOTE})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        module_name = f"hostlink.commands.{name.replace('-', '_')}"
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        p = sub.add_parser(
            name, help=module.HELP, description=getattr(module, "DESCRIPTION", module.HELP), epilog=DOCS_NOTE
        )
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def _one_line_warning(command: str):  # noqa: ANN202 - a warnings.showwarning replacement
    """Print a Python warning (an ERFA "dubious year" for a date past the leap-second table, say) as one line on
    stderr, ``hostlink COMMAND: warning: CATEGORY: message``, instead of Python's two lines with a source path."""

    def show(message, category, _filename, _lineno, _file=None, _line=None) -> None:  # noqa: ANN001
        text = " ".join(f"{category.__name__}: {message}".split())
        print(f"hostlink {command}: warning: {text}", file=sys.stderr)

    return show


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        with warnings.catch_warnings():  # a library's warning is one line too, named like the command's errors
            warnings.showwarning = _one_line_warning(args.command)
            code = args._run(args)
    except UserError as exc:
        print(f"hostlink {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"hostlink {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError as exc:
        if not _stdout_closed():
            return _internal_error(args.command, exc)
        return 128 + 13  # the reader of stdout went away (`| head`): quiet, as a shell tool killed by SIGPIPE
    except OSError as exc:
        if os.environ.get("HOSTLINK_DEBUG"):
            raise
        if not _users_file_error(exc):
            return _internal_error(args.command, exc)
        print(f"hostlink {args.command}: error: {_short(exc.filename)}: {exc.strerror}", file=sys.stderr)
        return UserError.exit_code
    except Exception as exc:  # noqa: BLE001 - the promise is one line, never a traceback
        if os.environ.get("HOSTLINK_DEBUG"):
            raise
        return _internal_error(args.command, exc)
    return int(code or 0)


#: errno names of the file errors a user causes with a path they give (too long, missing, not a folder, a folder,
#: no permission, read-only or full file system, a loop of links): reported as ``PATH: reason`` with exit 2 when a
#: command's own checks let one through, rather than as an internal error.
_USER_FILE_ERRNOS = (
    "ENAMETOOLONG",
    "ENOENT",
    "ENOTDIR",
    "EISDIR",
    "EACCES",
    "EPERM",
    "EROFS",
    "ENOSPC",
    "EDQUOT",
    "ELOOP",
    "EEXIST",
)
#: Longest path printed in a one-line error [characters] (a 5,000-character name is cut, its end kept).
_MAX_PATH_CHARS = 120


def _users_file_error(exc: OSError) -> bool:
    import errno

    codes = {getattr(errno, name) for name in _USER_FILE_ERRNOS if hasattr(errno, name)}
    return exc.errno in codes and exc.filename is not None and bool(exc.strerror)


def _short(path: object) -> str:
    text = os.fsdecode(path) if isinstance(path, (str, bytes, os.PathLike)) else str(path)
    return text if len(text) <= _MAX_PATH_CHARS else f"...{text[-_MAX_PATH_CHARS:]} ({len(text)} characters)"


def _internal_error(command: str, exc: BaseException) -> int:
    print(
        f"hostlink {command}: internal error: {type(exc).__name__}: {exc} (set HOSTLINK_DEBUG=1 for a traceback)",
        file=sys.stderr,
    )
    return 1


def _stdout_closed() -> bool:
    """True when stdout's reader is gone (a pipe whose read end closed: poll reports an error on it); stdout is then
    pointed at /dev/null so the interpreter's own flush at exit does not fail again."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
    except (AttributeError, OSError, ValueError):
        return False
    poller.register(fd, select.POLLOUT)
    if not any(events & select.POLLERR for _, events in poller.poll(0)):
        return False
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)
    return True


if __name__ == "__main__":
    sys.exit(main())
