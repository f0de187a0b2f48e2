"""Where the documentation is (issue 31): the Markdown pages ``docs/*.md``, the README and the changelog are
installed with the package (pyproject.toml ``[tool.setuptools.data-files]``: ``<prefix>/share/doc/
startracker-companion/``, the pages in its ``docs/``), so a help text that cites ``docs/<page>.md`` points at a file the
user has. ``hostlink --docs`` prints the folder and its pages. From a checkout, the checkout's own ``docs/``."""

from __future__ import annotations

from pathlib import Path

from hostlink.errors import DISTRIBUTION

#: Where the wheel installs the pages, relative to the installation prefix (pyproject.toml data-files).
INSTALLED_DOCS = f"share/doc/{DISTRIBUTION}/docs"
#: A page every installation has: how the folder is recognised.
MARKER_PAGE = "interfaces.md"


def docs_dir() -> Path | None:
    """The folder of the documentation pages: the checkout's ``docs/`` when running from one, else the installed
    copy (found through the distribution's installed-file list, wherever pip put the prefix: a virtual environment,
    ``--user``, a system prefix); None when neither exists (an install without the data files)."""
    checkout = Path(__file__).resolve().parent.parent / "docs"
    if (checkout / MARKER_PAGE).is_file():
        return checkout
    from importlib.metadata import PackageNotFoundError, distribution

    try:
        files = distribution(DISTRIBUTION).files or []
    except PackageNotFoundError:
        return None
    for f in files:
        if str(f).replace("\\", "/").endswith(f"{INSTALLED_DOCS}/{MARKER_PAGE}"):
            path = Path(distribution(DISTRIBUTION).locate_file(f)).resolve()
            return path.parent if path.is_file() else None
    return None


def docs_listing() -> str:
    """What ``hostlink --docs`` prints: the folder, then one page a line (or why there is none)."""
    where = docs_dir()
    if where is None:
        return (
            f"the documentation pages are not installed: reinstall {DISTRIBUTION} from its wheel or sdist "
            "(they are in its docs/ folder)"
        )
    pages = sorted(p.name for p in where.glob("*.md"))
    readme = where.parent / "README.md"
    lines = [str(where)] + [f"  {name}" for name in pages]
    if readme.is_file():
        lines.append(f"README: {readme}")
    return "\n".join(lines)
