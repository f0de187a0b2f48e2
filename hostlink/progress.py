"""THE progress bar (rich, on stderr) of every long job: ``hostlink stream``, ``bench``, ``simulate`` and ``replay``.
Silent when disabled or when stderr is not a terminal (a pipe or a log file gets no control characters)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def progress_bar(what: str, total: int | None, enabled: bool = True) -> Iterator[Callable[[int], None]]:
    """Yields ``advance(done)``; shows ``what`` done/total with a rate while the block runs (``total`` None: not
    known in advance, as for a session read in chunks)."""
    if not enabled or not sys.stderr.isatty():
        yield lambda done: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(what, total=total)
        yield lambda done: bar.update(task, completed=done)
