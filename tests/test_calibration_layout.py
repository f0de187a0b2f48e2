"""The calibration package stays readable (issue 29): its docstring names the modules that exist, no file is over
500 lines and no function over 80."""

import pkgutil
import re
from pathlib import Path

from layout_limits import too_long

import hostlink.calibration as calibration

PACKAGE = Path(calibration.__file__).parent


def test_package_docstring_names_exactly_its_modules():
    modules = {m.name for m in pkgutil.iter_modules(calibration.__path__)}
    named = set(re.findall(r"``(\w+)``", calibration.__doc__))
    assert named == modules


def test_no_file_over_500_lines_and_no_function_over_80():
    assert too_long(list(PACKAGE.glob("*.py")), PACKAGE) == ([], [])
