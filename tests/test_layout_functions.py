"""Functions stay short enough to read as named steps (the project's style: the algorithm visible in one function a
reader can follow): no function over 80 lines in the C firmware core, the Python model it mirrors (``onboard``), the
links, the port kit and the commands. The calibration package holds the same bound in test_calibration_layout.py."""

import ast
from importlib import resources
from pathlib import Path

import hostlink
import onboard

#: Lines from a function's signature to its closing brace or last statement, the bound the calibration package
#: already holds: a longer function is split into named steps, each mirrored by name between C and Python.
MAX_FUNCTION_LINES = 80

PYTHON_FOLDERS = (
    Path(onboard.__file__).parent,
    Path(hostlink.__file__).parent / "links",
    Path(hostlink.__file__).parent / "portkit",
    Path(hostlink.__file__).parent / "commands",
)


def _c_function_lengths(text: str) -> dict[str, int]:
    """Name -> lines of every function defined in a C file of the core's layout (the signature from column 0, the
    body's braces alone on their lines in column 0); one-line bodies are skipped."""
    lengths: dict[str, int] = {}
    signature: int | None = None
    start = name = None
    for number, line in enumerate(text.splitlines()):
        if line[:1].isalpha() and "(" in line and not line.rstrip().endswith((";", "}")):
            signature = number
        elif line == "{" and signature is not None:
            start, signature = signature, None
            name = text.splitlines()[start].split("(")[0].split()[-1].lstrip("*")
        elif line == "}" and start is not None:
            lengths[name] = number - start + 1
            start = None
    return lengths


def test_no_c_function_in_the_core_over_80_lines():
    folder = resources.files("onboard").joinpath("c")
    long_functions, counted = [], 0
    for source in sorted(folder.iterdir(), key=lambda p: p.name):
        if not source.name.endswith(".c"):
            continue
        lengths = _c_function_lengths(source.read_text())
        counted += len(lengths)
        long_functions += [f"{source.name}:{n} ({k})" for n, k in lengths.items() if k > MAX_FUNCTION_LINES]
    assert counted > 200  # the functions were found (the core defines some three hundred)
    assert not long_functions, long_functions


def test_the_c_scanner_measures_a_function_from_signature_to_closing_brace():
    text = "static int f(int a,\n             int b)\n{\n    return a + b;\n}\nvoid g(void) { }\n"
    assert _c_function_lengths(text) == {"f": 5}


def test_no_python_function_over_80_lines_in_the_checked_packages():
    long_functions = []
    for folder in PYTHON_FOLDERS:
        for path in sorted(folder.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                        long_functions.append(f"{path.relative_to(folder.parent)}:{node.name}")
    assert not long_functions, long_functions
