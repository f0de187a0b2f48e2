"""User-facing errors of the host tool: each becomes one clear line and a non-zero exit code in the CLI."""


class UserError(Exception):
    """Bad input or a failed operation that the user can fix; the CLI prints ``hostlink: error: <message>``."""

    exit_code = 2


class LinkError(UserError):
    """The link to a sensor failed (dropped, timed out, corrupt beyond recovery)."""

    exit_code = 3


class SensorRefused(UserError):
    """The sensor refused a command (NAK) and gave a reason."""

    exit_code = 4


def one_line(exc: BaseException, max_chars: int = 200) -> str:
    """A foreign exception's message as one line of at most ``max_chars`` characters (whitespace runs collapsed; the
    exception's type name when it has no message), for the one-line errors of the CLI."""
    return " ".join(str(exc).split())[:max_chars] or type(exc).__name__


#: The distribution that installs the ``hostlink`` package and console script (pyproject.toml ``[project] name``):
#: what ``pip install`` must be given, never ``hostlink`` (an unrelated project of that name is on the index).
DISTRIBUTION = "startracker-companion"


def install_hint(extra: str | None = None) -> str:
    """The pip command that installs this project's optional extra ``extra`` (or the project itself):
    ``pip install 'startracker-companion[dask]'``."""
    return f"pip install '{DISTRIBUTION}[{extra}]'" if extra else f"pip install '{DISTRIBUTION}'"
