"""pyserial URL handlers of the host (``serial.protocol_handler_packages`` entry): ``bufsocket://HOST:PORT``; and the
check every port URL passes before pyserial opens it (:func:`refuse_file_writing_url`)."""

from __future__ import annotations

import os
from urllib.parse import parse_qs, urlsplit

from hostlink.errors import UserError

#: Environment variable that allows a port URL to write a file (``spy://...?file=X``), when set to ``1``.
ALLOW_FILE_URLS_ENV = "HOSTLINK_ALLOW_URL_FILES"
#: pyserial URL handlers that write a file named in the URL: handler -> its query parameter (pyserial 3.5
#: ``serial.urlhandler.protocol_spy``: ``file=FILENAME`` opens FILENAME for writing, following symbolic links).
_FILE_WRITING = {"spy": "file"}


def refuse_file_writing_url(url: str, option: str = "--link") -> None:
    """Refuse (one-line UserError) a port URL whose pyserial handler would write a file (``spy://...?file=X``: a
    link string must not overwrite files as a side effect), unless the environment variable
    ``HOSTLINK_ALLOW_URL_FILES=1`` asks for it. ``spy://`` without ``file=`` (its log goes to stderr) is accepted."""
    scheme = url.partition("://")[0].lower()
    key = _FILE_WRITING.get(scheme)
    if key is None or os.environ.get(ALLOW_FILE_URLS_ENV) == "1":
        return
    if key in parse_qs(urlsplit(url).query, keep_blank_values=True):
        raise UserError(
            f"{option} {url}: the {scheme}:// handler would write the file given by {key}= (refused; set "
            f"{ALLOW_FILE_URLS_ENV}=1 to allow it, or leave {key}= out to log to stderr)"
        )
