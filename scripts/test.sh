#!/usr/bin/env bash
# The project's test command (README): installs into .venv if needed, then the import contract and the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[test]"
.venv/bin/lint-imports
.venv/bin/python -m pytest -q "$@"
