"""The documentation reaches an installed user (issue 31): pyproject.toml installs every docs/*.md page, the README
and the changelog as data files (the wheel test installs them and runs ``hostlink --docs``); from a checkout
``hostlink --docs`` prints the checkout's pages; every command's help ends by saying where the pages are."""

import tomllib
from pathlib import Path

from hostlink.cli import COMMANDS, DOCS_NOTE, build_parser, main
from hostlink.docs import INSTALLED_DOCS, docs_dir

ROOT = Path(__file__).resolve().parent.parent


def test_every_page_is_installed_with_the_package():
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["data-files"]
    assert data[INSTALLED_DOCS] == ["docs/*.md"]
    assert {"README.md", "CHANGELOG.md"} <= set(data[str(Path(INSTALLED_DOCS).parent)])
    assert (ROOT / "CHANGELOG.md").is_file()


def test_docs_option_prints_the_pages(capsys):
    try:
        main(["--docs"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out.splitlines()
    assert Path(out[0]) == docs_dir() == ROOT / "docs"
    assert {line.strip() for line in out[1:] if line.startswith("  ")} == {p.name for p in (ROOT / "docs").glob("*.md")}


def test_every_help_that_cites_a_page_says_where_the_pages_are():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and set(a.choices) >= set(COMMANDS) - {"import-can"})
    for name, p in sub.choices.items():
        text = p.format_help()
        assert " ".join(DOCS_NOTE.split()) in " ".join(text.split()), name
