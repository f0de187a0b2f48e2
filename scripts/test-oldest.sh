#!/usr/bin/env bash
# The suite on the oldest dependency versions pyproject.toml allows (scripts/constraints-oldest.txt), in its own
# virtual environment .venv-oldest, so the lower bounds are tested as well as the newest versions.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-oldest/bin/python ]; then
  python3 -m venv .venv-oldest
fi
.venv-oldest/bin/python -m pip install --quiet --disable-pip-version-check -c scripts/constraints-oldest.txt -e ".[test]"
.venv-oldest/bin/python -m pytest -q -p no:cacheprovider "$@"
