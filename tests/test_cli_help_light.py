"""``hostlink --help`` and every sub-command's ``--help`` load no heavy third-party package (a help text is read in
a fresh interpreter, numpy alone costs ~0.05 s of import and the whole stack ~0.4 s): the parser is built from
option values kept in modules that import nothing (``hostlink.sky.attitude_choices``, ``protocol.names``). Pinned
as a property (what ``sys.modules`` holds after the help text), not a timing; the time is measured with
``python -X importtime`` (CHANGELOG.md)."""

import json
import subprocess
import sys

from test_api_import_light import HEAVY

from hostlink.cli import COMMANDS

_PROBE = (
    "import contextlib, io, json, sys\n"
    "from hostlink.cli import main\n"
    "out = io.StringIO()\n"
    "with contextlib.redirect_stdout(out):\n"
    "    try:\n"
    "        code = main(json.loads(sys.argv[1]))\n"
    "    except SystemExit as exc:\n"
    "        code = exc.code\n"
    "print(json.dumps([code, len(out.getvalue()), sorted({m.split('.')[0] for m in sys.modules})]))\n"
)


def _help_modules(argv: list[str]) -> tuple[int, int, set[str]]:
    run = subprocess.run(
        [sys.executable, "-c", _PROBE, json.dumps(argv)], capture_output=True, text=True, timeout=120, check=True
    )
    code, n_chars, modules = json.loads(run.stdout)
    return code, n_chars, set(modules)


def test_top_level_help_loads_no_heavy_package():
    code, n_chars, modules = _help_modules(["--help"])
    assert code == 0 and n_chars > 0
    assert modules.isdisjoint(HEAVY), sorted(modules & set(HEAVY))


def test_every_sub_command_help_loads_no_heavy_package():
    heavy = {}
    for command in COMMANDS:
        code, n_chars, modules = _help_modules([command, "--help"])
        assert code == 0 and n_chars > 0, command
        if modules & set(HEAVY):
            heavy[command] = sorted(modules & set(HEAVY))
    assert heavy == {}


def test_the_light_option_values_are_the_solvers_own():
    """The commands' choices come from the light modules; the solver and the parameter layout use the same objects."""
    from hostlink import api
    from hostlink.sky import attitude, attitude_choices
    from protocol import names, param_table

    assert attitude.REFRACTION_MODES is attitude_choices.REFRACTION_MODES is api.REFRACTION_MODES
    assert attitude.DEFAULT_REJECT_ARCSEC == attitude_choices.DEFAULT_REJECT_ARCSEC == api.DEFAULT_REJECT_ARCSEC
    assert param_table.ESTIMATE_NAMES is names.ESTIMATE_NAMES is api.ESTIMATE_NAMES
    assert param_table.DISTORTION_NAMES is names.DISTORTION_NAMES is api.DISTORTION_NAMES
