"""Functions stay short enough to read as named steps (the project's style: the algorithm visible in one function a
reader can follow): no function over 80 lines in the C firmware core, the Python model it mirrors (``onboard``), the
links, the port kit and the commands. The calibration package holds the same bound in test_calibration_layout.py."""

from importlib import resources
from pathlib import Path

from layout_limits import MAX_FUNCTION_LINES, too_long

import hostlink
import onboard

# MAX_FUNCTION_LINES: lines from a function's signature to its closing brace or last statement; a longer function
# is split into named steps, each mirrored by name between C and Python.

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
    long_functions = [f for folder in PYTHON_FOLDERS for f in too_long(list(folder.rglob("*.py")), folder.parent)[1]]
    assert not long_functions, long_functions
