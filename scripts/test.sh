#!/usr/bin/env bash
# The project's test command (README): installs into .venv if needed (the newest dependency versions pyproject.toml
# allows), then lint and format checks, the import contract and the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[test,cosmos]"
.venv/bin/ruff check --quiet .
.venv/bin/ruff format --check --quiet .
.venv/bin/lint-imports
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
# The link, emulator and bench suites once more against the C firmware core (issue 27: hostlink emulate reads its
# default --firmware from HOSTLINK_FIRMWARE), in this newest-versions pass only, when a C compiler is present and
# the whole suite was asked for.
if [ "$#" -eq 0 ] && command -v "${CC:-cc}" >/dev/null; then
  HOSTLINK_FIRMWARE=c .venv/bin/python -m pytest -q -p no:cacheprovider tests/test_link_*.py tests/test_emulator_*.py \
    tests/test_bench_end_to_end.py tests/test_soak_short.py tests/test_upload_plausibility_cli.py
fi
