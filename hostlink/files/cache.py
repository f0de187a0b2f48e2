"""The project's user cache directory: ``$XDG_CACHE_HOME/startracker-companion``, else
``~/.cache/startracker-companion`` (the XDG base directory rule). Everything the package caches (the parsed
Hipparcos catalogue, the solver's pattern database, the C firmware core's host and Cortex-M builds) lives below it,
so one place names it."""

from __future__ import annotations

import os
from pathlib import Path

#: The directory below the user cache that belongs to this project.
CACHE_NAME = "startracker-companion"


def cache_dir() -> Path:
    """The user cache directory of this project (not created here)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / CACHE_NAME
