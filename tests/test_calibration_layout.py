"""The calibration package stays readable (issue 29): its docstring names the modules that exist, no file is over
500 lines and no function over 80."""

import ast
import pkgutil
import re
from pathlib import Path

import hostlink.calibration as calibration

PACKAGE = Path(calibration.__file__).parent
MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 80


def test_package_docstring_names_exactly_its_modules():
    modules = {m.name for m in pkgutil.iter_modules(calibration.__path__)}
    named = set(re.findall(r"``(\w+)``", calibration.__doc__))
    assert named == modules


def test_no_file_over_500_lines_and_no_function_over_80():
    long_files, long_functions = [], []
    for path in sorted(PACKAGE.glob("*.py")):
        text = path.read_text()
        if text.count("\n") > MAX_FILE_LINES:
            long_files.append(path.name)
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                    long_functions.append(f"{path.name}:{node.name}")
    assert not long_files and not long_functions, (long_files, long_functions)
