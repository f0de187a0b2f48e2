"""The one atomic file writer (docs/architecture.md: hostlink/files): every file the host writes goes through it.

A file is written whole or not at all: the bytes go to a temporary file in the same directory (``PATH.<pid>.tmp``,
or a name the caller chooses, such as a session's ``PATH.partial``), which is flushed, ``fsync``-ed and renamed onto
``PATH`` (``os.replace``: atomic on POSIX and Windows within one file system); the directory is then ``fsync``-ed so
the rename itself survives a power cut. A reader therefore sees the old file or the new one, never half of either.
A write that fails removes its temporary file and raises a one-line :class:`hostlink.errors.UserError` naming
``PATH``. The process id in the default temporary name keeps two processes writing the same file (a catalogue cache
filled by two commands at once) from mixing their bytes.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from hostlink.errors import UserError


def file_path(path: str | Path) -> Path:
    """``path`` as a Path, refused in one line (:class:`UserError`) when it names no file: empty, ``.``, ``..`` or a
    root (an empty ``--out ""`` would otherwise reach pathlib's ValueError)."""
    p = Path(path)
    if not str(path) or p.name in ("", ".", ".."):
        raise UserError(f"{str(path)!r}: not a file name")
    return p


def cannot_write(path: str | Path, exc: OSError) -> UserError:
    """The one-line error for a file that cannot be written."""
    return UserError(f"{path}: cannot write ({exc.strerror or exc})")


class AtomicFile:
    """``PATH`` written through a temporary file in its directory and renamed into place by :meth:`commit`.

    ``temporary``: the temporary file's path (default ``PATH.<pid>.tmp``; it must be in PATH's directory).
    ``binary``: open in ``"wb"`` mode; otherwise text, UTF-8, with ``newline`` as :func:`open` takes it.
    Missing parent directories are created. Use :meth:`open` to get the handle, then :meth:`commit` or
    :meth:`abandon`; or use it as a context manager: a normal exit commits, an exception abandons (removes the
    temporary file unless ``keep_on_error``)."""

    def __init__(
        self,
        path: str | Path,
        *,
        temporary: str | Path | None = None,
        binary: bool = False,
        newline: str | None = None,
        keep_on_error: bool = False,
    ) -> None:
        self.path = file_path(path)
        self.temporary = (
            Path(temporary) if temporary is not None else self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
        )
        if self.temporary.parent != self.path.parent:
            raise ValueError(f"{self.temporary}: the temporary file must be in the directory of {self.path}")
        self.binary = binary
        self.newline = newline
        self.keep_on_error = keep_on_error
        self.handle: IO | None = None

    def open(self) -> IO:
        """Create the temporary file and return its handle (text or binary as configured)."""
        if self.handle is None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                if self.binary:
                    self.handle = self.temporary.open("wb")
                else:
                    self.handle = self.temporary.open("w", encoding="utf-8", newline=self.newline)
            except OSError as exc:
                raise cannot_write(self.path, exc) from None
        return self.handle

    def commit(self) -> None:
        """Flush, fsync and close the temporary file, rename it onto ``path`` and fsync the directory. A temporary
        file already closed (kept by :meth:`abandon`) is renamed as it is."""
        handle = self.open()
        try:
            if not handle.closed:
                handle.flush()
                os.fsync(handle.fileno())
                handle.close()
            os.replace(self.temporary, self.path)
        except OSError as exc:
            self.abandon(keep=False)
            raise cannot_write(self.path, exc) from None
        _fsync_directory(self.path.parent)

    def abandon(self, keep: bool = False) -> None:
        """Close without renaming; the temporary file is removed unless ``keep``."""
        if self.handle is not None and not self.handle.closed:
            try:
                self.handle.close()
            except OSError:
                pass  # the write is abandoned anyway; the error that got us here is the one to report
        if not keep:
            try:
                self.temporary.unlink(missing_ok=True)
            except OSError:
                pass  # never created (a name too long, a folder not writable): the error that got us here stands

    def __enter__(self) -> IO:
        return self.open()

    def __exit__(self, exc_type, exc, _tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abandon(keep=self.keep_on_error)
            if isinstance(exc, OSError):
                raise cannot_write(self.path, exc) from None


def _fsync_directory(directory: Path) -> None:
    # POSIX only: a directory cannot be opened for fsync on Windows, where the rename is durable by itself
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on a directory; the rename has still happened
    finally:
        os.close(fd)


@contextmanager
def atomic_open(path: str | Path, *, binary: bool = False, newline: str | None = None) -> Iterator[IO]:
    """``with atomic_open(PATH) as handle:`` write PATH atomically (see :class:`AtomicFile`)."""
    with AtomicFile(path, binary=binary, newline=newline) as handle:
        yield handle


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_open(path) as handle:
        handle.write(text)


def json_text(data: Any, *, indent: int | None = 2, default: Callable[[Any], Any] | None = None) -> str:
    """The project's JSON text of ``data``: strict JSON (a NaN or infinity is refused: ValueError), one object, a
    final newline; ``indent=None`` writes it compact."""
    separators = (",", ":") if indent is None else None
    return json.dumps(data, indent=indent, separators=separators, allow_nan=False, default=default) + "\n"


def write_json(
    path: str | Path, data: Any, *, indent: int | None = 2, default: Callable[[Any], Any] | None = None
) -> None:
    """Write ``data`` as strict JSON (:func:`json_text`) to ``path`` atomically."""
    write_text(path, json_text(data, indent=indent, default=default))


def save_figure(path: str | Path, figure: Any, dpi: int = 110) -> None:
    """Write a matplotlib figure as PNG to ``path`` atomically (plots of reports: ``hostlink bench``,
    ``hostlink calibrate --plot``)."""
    with atomic_open(path, binary=True) as handle:
        figure.savefig(handle, format="png", dpi=dpi)
