"""The public surface: every name ``hostlink.api`` documents resolves, the judge (truth generators and Cramer-Rao
bounds) is part of it, and the tests reach commands only through the console script, never by importing a command
module (the commands themselves import only ``hostlink.api``: an import-linter contract in pyproject.toml)."""

from __future__ import annotations

import ast
from pathlib import Path

import hostlink.api as api

TESTS = Path(__file__).resolve().parent


def test_every_documented_name_resolves():
    missing = [name for name in api.__all__ if not hasattr(api, name)]
    assert missing == []
    assert len(set(api.__all__)) == len(api.__all__)


def test_the_judge_is_in_the_api():
    for name in (
        "synthetic_session",
        "make_frames",
        "fisher_information",
        "validation_residual_px",
        "crb_validation_px",
        "interstar_information",
        "attitude_covariance",
    ):
        assert name in api.__all__, name


def _imported_modules(tree: ast.AST) -> set[str]:
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def test_no_test_imports_a_command_module():
    offenders = []
    for path in sorted(TESTS.glob("*.py")):
        modules = _imported_modules(ast.parse(path.read_text(encoding="utf-8")))
        offenders += [f"{path.name}: {m}" for m in sorted(modules) if m.startswith("hostlink.commands")]
    assert offenders == []
