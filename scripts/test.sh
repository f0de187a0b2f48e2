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
