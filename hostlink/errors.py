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
