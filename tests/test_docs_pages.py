"""The repository stands alone: every document or file it cites (in code, docstrings, help texts, docs, scripts) is
in it; and docs/commands.md says what ``hostlink COMMAND --help`` says (scripts/gen_command_docs.py --check)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Folders that are not the repository's own text: version control, environments, caches, build output, reports.
SKIP_DIRS = {".git", ".venv", "venv", "__pycache__", ".pytest_cache", ".hypothesis", ".ruff_cache", "build", "dist"}
SKIP_DIR_SUFFIXES = (".egg-info",)
#: Generated output folders a run may leave in a checkout (the bench's default report folder).
SKIP_GENERATED = {"bench-report"}
#: Larger files are data (catalogues, captures), not prose that cites.
MAX_TEXT_BYTES = 2_000_000

#: A cited Markdown document: any word ending in ``.md`` (``README.md``, ``docs/links.md``, ``../README.md``).
_MD_RE = re.compile(r"(?<![\w./-])([\w./-]*\w\.md)\b")
#: A cited repository path: a top-level folder of the repository, then a file name with a known extension.
_PATH_RE = re.compile(
    r"(?<![\w./:-])((?:onboard|protocol|hostlink|tests|benchmarks|scripts|docs)/[\w./-]*\w\."
    r"(?:py|md|json|csv|dbc|sh|toml|c|h|txt))\b"
)


def citations(text: str) -> list[tuple[int, str]]:
    """(line number, cited name) of every Markdown document and repository path named in ``text``."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for name in sorted(set(_MD_RE.findall(line)) | set(_PATH_RE.findall(line))):
            found.append((number, name))
    return found


def resolves(name: str, citing: Path, root: Path) -> bool:
    """A citation resolves when the file exists beside the citing file, at the repository root, or in docs/ (the
    pages cite each other by bare name, the code cites them as docs/NAME or by bare name)."""
    bare = name.removeprefix("./")
    return any(c.is_file() for c in (citing.parent / name, root / bare, root / "docs" / bare))


def _repository_files(root: Path) -> list[Path] | None:
    """The repository's own files: tracked, or new and not ignored (``git ls-files``), so environments and outputs
    that .gitignore names (.venv-oldest, reports) are never read; None outside a git checkout."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=root,
            capture_output=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    return [root / name for name in listed.decode("utf-8").split("\0") if name]


def _walked_files(root: Path):
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [
            d for d in dirnames if d not in SKIP_DIRS and d not in SKIP_GENERATED and not d.endswith(SKIP_DIR_SUFFIXES)
        ]
        for name in filenames:
            yield Path(dirpath) / name


def text_files(root: Path):
    listed = _repository_files(root) if (root / ".git").exists() else None
    for path in _walked_files(root) if listed is None else listed:
        if not path.is_file() or path.stat().st_size > MAX_TEXT_BYTES:
            continue
        try:
            yield path, path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue  # binary (images, flash images, Parquet)


def broken_citations(root: Path) -> list[str]:
    return [
        f"{path.relative_to(root)}:{number}: {name}"
        for path, text in text_files(root)
        for number, name in citations(text)
        if not resolves(name, path, root)
    ]


def test_detector_finds_a_missing_document_and_accepts_present_ones(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "camera-model.md").write_text("see [file formats](file-formats.md)\n")
    (tmp_path / "docs" / "file-formats.md").write_text("# formats\n")
    (tmp_path / "pkg").mkdir()
    md = ".md"  # the missing names are built here, so this file cites nothing missing itself
    missing, missing_doc = "SPEC_MODEL" + md, "docs/nothere" + md
    (tmp_path / "pkg" / "mod.py").write_text(
        f'"""The model (docs/camera-model{md}, {missing}); see camera-model{md}."""\nHELP = "formats: {missing_doc}"\n'
    )
    assert sorted(broken_citations(tmp_path)) == [f"pkg/mod.py:1: {missing}", f"pkg/mod.py:2: {missing_doc}"]


def test_every_cited_file_is_in_the_repository():
    broken = broken_citations(ROOT)
    assert not broken, "citations of files not in the repository:\n" + "\n".join(broken)


def test_command_reference_is_current():
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gen_command_docs.py"), "--check"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stdout + done.stderr
