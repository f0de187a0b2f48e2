"""``hostlink export-c DIR`` and ``hostlink export-ground DIR`` write all their files or none (the files built in a
temporary directory, moved into place only when complete: ``hostlink.files.atomic.write_tree``). A write that fails
late (disk full at the third file, a rename refused half-way, a directory in the way, a file where DIR should be)
leaves DIR as it was, no temporary directory behind, and says so in one line with exit code 2."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from hostlink.cli import main
from hostlink.files import atomic

COMMANDS = ("export-c", "export-ground")


def _snapshot(root: Path) -> dict[str, bytes | None]:
    """Every entry under ``root`` (hidden ones included): relative path -> file bytes (None for a folder)."""
    out: dict[str, bytes | None] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for d in dirnames:
            out[os.path.relpath(os.path.join(dirpath, d), root)] = None
        for f in filenames:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = Path(p).read_bytes()
    return out


def _run(command: str, directory: Path, capsys) -> tuple[int, str, str]:
    code = main([command, str(directory)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _fail_at_call(monkeypatch, module, name: str, n: int) -> None:
    """``module.name`` raises ENOSPC (disk full) at its ``n``-th call, as a disk that fills up midway."""
    real = getattr(module, name)
    calls = {"n": 0}

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, failing)


def _one_line_refusal(code: int, out: str, err: str) -> None:
    assert code == 2, err
    assert out == "" and len(err.strip().splitlines()) == 1 and "nothing written" in err and "Traceback" not in err


@pytest.mark.parametrize("command", COMMANDS)
def test_a_disk_full_midway_leaves_no_new_directory(command, tmp_path, capsys, monkeypatch):
    _fail_at_call(monkeypatch, atomic, "_write_new_file", 3)
    _one_line_refusal(*_run(command, tmp_path / "out" / "kit", capsys))
    assert _snapshot(tmp_path) == {}  # neither DIR, nor its parent made for it, nor a temporary directory


@pytest.mark.parametrize("command", COMMANDS)
def test_a_disk_full_midway_leaves_an_existing_export_as_it_was(command, tmp_path, capsys, monkeypatch):
    kit = tmp_path / "kit"
    assert _run(command, kit, capsys)[0] == 0  # a previous export
    (kit / "notes.txt").write_text("the user's own file\n")
    first = sorted(kit.rglob("*"))[0]
    if first.is_file():
        first.write_text("an older version\n")
    before = _snapshot(tmp_path)
    _fail_at_call(monkeypatch, atomic, "_write_new_file", 3)
    _one_line_refusal(*_run(command, kit, capsys))
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_a_rename_that_fails_half_way_is_undone(command, tmp_path, capsys, monkeypatch):
    """Into an existing DIR the files are renamed one by one: the fourth rename of a file into place fails; the
    three placed before are taken back and the files they replaced put back."""
    kit = tmp_path / "kit"
    assert _run(command, kit, capsys)[0] == 0
    for p in kit.rglob("*"):
        if p.is_file():
            p.write_text(f"old {p.name}\n")
    before = _snapshot(tmp_path)
    real = os.rename
    placed = {"n": 0}

    def rename(src, dst, *args, **kwargs):
        if ".replaced" not in f"{src}{dst}" and ".tmp" in str(src) and ".tmp" not in str(dst):
            placed["n"] += 1  # a staged file moved into place
            if placed["n"] == 4:
                raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(atomic.os, "rename", rename)
    _one_line_refusal(*_run(command, kit, capsys))
    assert placed["n"] == 4
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_a_directory_in_the_way_of_a_file_is_found_before_anything_is_written(command, tmp_path, capsys):
    kit = tmp_path / "kit"
    assert _run(command, kit, capsys)[0] == 0
    last = sorted(p for p in kit.rglob("*") if p.is_file())[-1]
    last.unlink()
    last.mkdir()  # a directory where the export puts a file
    before = _snapshot(tmp_path)
    code, out, err = _run(command, kit, capsys)
    _one_line_refusal(code, out, err)
    assert "in the way" in err
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_a_file_where_dir_should_be_is_refused(command, tmp_path, capsys):
    (tmp_path / "kit").write_text("a file\n")
    code, out, err = _run(command, tmp_path / "kit", capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and "not a directory" in err
    assert (tmp_path / "kit").read_text() == "a file\n" and len(list(tmp_path.iterdir())) == 1


@pytest.mark.parametrize("command", COMMANDS)
def test_an_unwritable_parent_is_a_one_line_refusal(command, tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes into a read-only folder")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        _one_line_refusal(*_run(command, locked / "kit", capsys))
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_complete_export_replaces_old_files_and_keeps_the_users_own(command, tmp_path, capsys):
    kit = tmp_path / "kit"
    code, out, _ = _run(command, kit, capsys)
    assert code == 0
    written = [Path(line) for line in out.splitlines()]
    fresh = {p: p.read_bytes() for p in written}
    for p in written:
        p.write_text("old\n")
    (kit / "notes.txt").write_text("mine\n")
    assert _run(command, kit, capsys)[0] == 0
    assert {p: p.read_bytes() for p in written} == fresh
    assert (kit / "notes.txt").read_text() == "mine\n"
    assert not [p for p in tmp_path.rglob(".*")]  # no temporary directory left


@pytest.mark.parametrize("command", COMMANDS)
def test_the_current_folder_is_a_directory_to_export_into(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, _ = _run(command, Path("."), capsys)
    assert code == 0 and out.splitlines() and all(Path(line).is_file() for line in out.splitlines())
    assert not [p for p in tmp_path.rglob(".*")]
