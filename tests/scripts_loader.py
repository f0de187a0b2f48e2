"""The scripts of ``scripts/`` (the long runs: fuzzing, soak, power cuts, option sweep) as modules, so that the short
versions in the test suite judge with the long runs' own generators and oracles."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(filename: str) -> ModuleType:
    """``scripts/FILENAME`` loaded once per test process (as module ``hostlink_script_STEM``)."""
    path = SCRIPTS / filename
    name = f"hostlink_script_{path.stem}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # a script's dataclasses resolve their annotations through sys.modules
    spec.loader.exec_module(module)
    return module
