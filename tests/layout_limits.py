"""The readability limits the layout tests hold (the project's style: an algorithm visible in one function a reader
can follow): a Python module at most 500 lines, a function (signature to last statement) at most 80; what is longer is
split into named modules and steps."""

import ast
from pathlib import Path

MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80


def too_long(paths: list[Path], root: Path) -> tuple[list[str], list[str]]:
    """(modules over :data:`MAX_FILE_LINES`, functions over :data:`MAX_FUNCTION_LINES` as ``module:function``) among
    ``paths``, each named relative to ``root``."""
    long_files, long_functions = [], []
    for path in sorted(paths):
        text = path.read_text()
        name = str(path.relative_to(root))
        if text.count("\n") > MAX_FILE_LINES:
            long_files.append(name)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                    long_functions.append(f"{name}:{node.name}")
    return long_files, long_functions
