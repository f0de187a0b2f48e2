"""The one atomic file writer (docs/architecture.md: hostlink/files): every file the host writes goes through it.

A file is written whole or not at all, and never through a symbolic link: the bytes go to a temporary file created
exclusively in the same directory (``os.open`` with ``O_CREAT | O_EXCL | O_NOFOLLOW``: a file or symbolic link
already at that name is never opened, a new name is drawn instead) under an unpredictable name
(``.NAME.<16 random hex digits>.tmp``, or ``.partial`` for a session being streamed: 64 bits from the operating
system's random source, so a name cannot be planted in advance). It is flushed, ``fsync``-ed and renamed onto
``PATH`` (``os.replace``: atomic on POSIX and Windows within one file system; a symbolic link at ``PATH`` is
replaced by the file, the file it pointed to is left alone); the directory is then ``fsync``-ed so the rename itself
survives a power cut. A reader therefore sees the old file or the new one, never half of either. A write that fails
removes its temporary file and raises a one-line :class:`hostlink.errors.UserError` naming ``PATH``. Two processes
writing the same file (a catalogue cache filled by two commands at once) never share a temporary file.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
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


#: Random bytes in a temporary file's name (64 bits: a name cannot be guessed ahead and planted).
_TOKEN_BYTES = 8
#: Names drawn before giving up when every one is taken (each is taken with probability ~0 unless planted).
_NAME_TRIES = 16
#: Flags of a temporary file: created here and now, never an existing file, never through a symbolic link.
_CREATE_FLAGS = (
    os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
) | getattr(os, "O_BINARY", 0)


def _token() -> str:
    return secrets.token_hex(_TOKEN_BYTES)


def temporary_name(path: Path, suffix: str = ".tmp") -> Path:
    """A fresh temporary file name next to ``path``: ``.NAME.<random hex>SUFFIX`` (hidden, unpredictable)."""
    return path.with_name(f".{path.name}.{_token()}{suffix}")


def create_exclusive(path: Path, suffix: str = ".tmp") -> tuple[int, Path]:
    """Create a new temporary file next to ``path`` (:func:`temporary_name`) and return its descriptor (open for
    writing) and name. A name already taken (by anything, a planted symbolic link included) is never opened: the
    next one is drawn. Raises OSError (FileExistsError after _NAME_TRIES taken names)."""
    for _ in range(_NAME_TRIES):
        temporary = temporary_name(path, suffix)
        try:
            return os.open(temporary, _CREATE_FLAGS, 0o666), temporary  # mode as open() gives, less the umask
        except FileExistsError:
            continue
    raise FileExistsError(f"{_NAME_TRIES} temporary names next to {path.name} are taken")


class AtomicFile:
    """``PATH`` written through a temporary file created exclusively in its directory (:func:`create_exclusive`)
    and renamed onto it by :meth:`commit`.

    ``suffix``: the temporary name's ending (``.tmp``; a session being streamed: ``.partial``); :attr:`temporary` is
    its path once :meth:`open` has created it. ``binary``: open in ``"wb"`` mode; otherwise text, UTF-8, with
    ``newline`` as :func:`open` takes it. ``durable``: ``fsync`` the file and its directory at :meth:`commit` (off
    only for scratch files that do not outlive the process). Missing parent directories are created. Use :meth:`open`
    to get the handle, then :meth:`commit` or :meth:`abandon`; or use it as a context manager: a normal exit
    commits, an exception abandons (removes the temporary file unless ``keep_on_error``)."""

    def __init__(
        self,
        path: str | Path,
        *,
        suffix: str = ".tmp",
        binary: bool = False,
        newline: str | None = None,
        keep_on_error: bool = False,
        durable: bool = True,
    ) -> None:
        self.path = file_path(path)
        self.suffix = suffix
        self.temporary: Path | None = None
        self.binary = binary
        self.newline = newline
        self.keep_on_error = keep_on_error
        self.durable = durable
        self.handle: IO | None = None

    def open(self) -> IO:
        """Create the temporary file and return its handle (text or binary as configured)."""
        if self.handle is None:
            try:
                for folder in (self.path.parent, *self.path.parent.parents):
                    if folder.exists() or folder.is_symlink():
                        if not folder.is_dir():  # mkdir would say "File exists" of the file in the way
                            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
                        break
                self.path.parent.mkdir(parents=True, exist_ok=True)
                fd, self.temporary = create_exclusive(self.path, self.suffix)
                if self.binary:
                    self.handle = os.fdopen(fd, "wb")
                else:
                    self.handle = os.fdopen(fd, "w", encoding="utf-8", newline=self.newline)
            except OSError as exc:
                raise cannot_write(self.path, exc) from None
        return self.handle

    def commit(self) -> None:
        """Flush, fsync and close the temporary file, rename it onto ``path`` (replacing a symbolic link there, never
        writing through it) and fsync the directory. A temporary file already closed (kept by :meth:`abandon`) is
        renamed as it is."""
        handle = self.open()
        try:
            if not handle.closed:
                handle.flush()
                if self.durable:
                    os.fsync(handle.fileno())
                handle.close()
            os.replace(self.temporary, self.path)
        except OSError as exc:
            self.abandon(keep=False)
            raise cannot_write(self.path, exc) from None
        if self.durable:
            _fsync_directory(self.path.parent)

    def abandon(self, keep: bool = False) -> None:
        """Close without renaming; the temporary file is removed unless ``keep``."""
        if self.handle is not None and not self.handle.closed:
            try:
                self.handle.close()
            except OSError:
                pass  # the write is abandoned anyway; the error that got us here is the one to report
        if not keep and self.temporary is not None:
            try:
                self.temporary.unlink(missing_ok=True)
            except OSError:
                pass  # the error that got us here stands

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
def atomic_open(
    path: str | Path, *, binary: bool = False, newline: str | None = None, durable: bool = True
) -> Iterator[IO]:
    """``with atomic_open(PATH) as handle:`` write PATH atomically (see :class:`AtomicFile`)."""
    with AtomicFile(path, binary=binary, newline=newline, durable=durable) as handle:
        yield handle


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, binary=True) as handle:
        handle.write(data)


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


def _write_new_file(path: Path, data: bytes) -> None:
    """Create ``path`` (never an existing file, never through a symbolic link), write ``data``, fsync and close."""
    fd = os.open(path, _CREATE_FLAGS, 0o666)
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


def _tree_conflict(directory: Path, names: list[str]) -> str | None:
    """What in ``directory`` stands in the way of writing the files ``names`` (relative, ``/``-separated): a
    directory where a file goes, or something other than a directory where a folder goes; None when nothing does."""
    for name in names:
        parts = name.split("/")
        for k in range(1, len(parts)):
            folder = directory.joinpath(*parts[:k])
            if folder.exists() and not folder.is_dir():
                return f"{folder}: in the way of the folder {'/'.join(parts[:k])} (not a directory)"
        target = directory / name
        if target.is_dir() and not target.is_symlink():
            return f"{target}: a directory is in the way of the file {name}"
    return None


def write_tree(directory: str | Path, files: dict[str, str | bytes]) -> list[Path]:
    """Write a set of files (relative name, ``/`` for sub-folders -> text or bytes) under ``directory`` all at once,
    or none of them: the files are built in a temporary directory (``.NAME.<random hex>.tmp``, created exclusively:
    beside ``directory`` when it does not exist yet, else inside it) and moved into place only when every one is
    complete. A new ``directory`` is the temporary one renamed (atomic); in an existing one each file is renamed onto
    its place (a file already there replaced, never written through a symbolic link) after a check that nothing
    stands in the way, and the files replaced so far are put back if a rename fails. On any failure nothing new is
    left behind (the temporary directory, and the folders created for it, removed) and a one-line
    :class:`UserError` names ``directory``. Returns the paths written, in the order of ``files``."""
    if not str(directory):
        raise UserError("'': not a directory name")
    given = Path(directory)
    out = Path(os.path.abspath(given))  # "." and ".." named by what they are (the temporary name is made from it)
    names = list(files)
    if out.exists() and not out.is_dir():
        raise UserError(f"{given}: not a directory")
    created: list[Path] = []  # parent folders this call made (removed again on failure)
    try:
        for parent in reversed([out.parent, *out.parent.parents]):
            if not parent.exists():
                parent.mkdir()
                created.append(parent)
        fresh = not out.exists()
        conflict = None if fresh else _tree_conflict(out, names)
        if conflict is not None:
            raise UserError(f"{given}: nothing written: {conflict}")
        staging = _make_staging(out if fresh else out / out.name)
    except OSError as exc:
        _remove_folders(created)
        raise UserError(f"{given}: cannot write ({exc.strerror or exc}); nothing written") from None
    except UserError:
        _remove_folders(created)
        raise
    try:
        for name in names:
            data = files[name]
            path = staging / name
            path.parent.mkdir(parents=True, exist_ok=True)
            _write_new_file(path, data.encode("utf-8") if isinstance(data, str) else bytes(data))
        if fresh:
            os.rename(staging, out)
            _fsync_directory(out.parent)
        else:
            _move_into(staging, out, names)
    except OSError as exc:
        _remove_tree(staging)
        _remove_folders(created)
        raise UserError(f"{given}: cannot write ({exc.strerror or exc}); nothing written") from None
    except BaseException:
        _remove_tree(staging)
        _remove_folders(created)
        raise
    if not fresh:
        _remove_tree(staging)
    return [given / name for name in names]


def _make_staging(anchor: Path) -> Path:
    """A new, empty temporary directory named after ``anchor`` (:func:`temporary_name`, in ``anchor``'s folder),
    created exclusively: a name already taken (a planted symbolic link included) is never used, another is drawn."""
    for _ in range(_NAME_TRIES):
        staging = temporary_name(anchor)
        try:
            staging.mkdir()
            return staging
        except FileExistsError:
            continue
    raise FileExistsError(f"{_NAME_TRIES} temporary names next to {anchor.name} are taken")


def _move_into(staging: Path, out: Path, names: list[str]) -> None:
    """Rename each staged file onto its place under ``out``; on a failure, undo: the new files removed, the files
    they replaced (kept aside in ``staging/.replaced``) renamed back, the folders made removed."""
    aside = staging / ".replaced"
    aside.mkdir()
    done: list[tuple[Path, Path | None]] = []  # (placed file, the file it replaced kept aside)
    made: list[Path] = []
    try:
        for k, name in enumerate(names):
            target = out / name
            for folder in reversed([target.parent, *target.parent.parents]):
                if folder != out and out in folder.parents and not folder.exists():
                    folder.mkdir()
                    made.append(folder)
            old = None
            if target.exists() or target.is_symlink():
                old = aside / str(k)
                os.rename(target, old)
            try:
                os.rename(staging / name, target)
            except OSError:
                if old is not None:
                    os.rename(old, target)
                raise
            done.append((target, old))
    except OSError:
        for target, old in reversed(done):
            try:
                if old is not None:
                    os.replace(old, target)
                else:
                    target.unlink()
            except OSError:
                pass  # the first error is the one reported
        _remove_folders(made)
        raise
    for folder in sorted({(out / name).parent for name in names}):
        _fsync_directory(folder)


def _remove_tree(path: Path) -> None:
    import shutil

    shutil.rmtree(path, ignore_errors=True)


def _remove_folders(folders: list[Path]) -> None:
    """Remove folders this process created, innermost first, each only if empty."""
    for folder in reversed(folders):
        try:
            folder.rmdir()
        except OSError:
            pass
