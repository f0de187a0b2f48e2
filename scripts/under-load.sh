#!/usr/bin/env bash
# Runs a command with two CPU-bound busy loops beside it (a 2-core machine fully loaded), to show that nothing in the
# project depends on how fast the host happens to be. Examples:
#   bash scripts/under-load.sh bash .ci/run
#   bash scripts/under-load.sh .venv/bin/hostlink bench --transport can --quiet
set -euo pipefail
[ $# -gt 0 ] || { echo "usage: scripts/under-load.sh COMMAND [ARGS...]" >&2; exit 2; }
pids=()
for _ in 1 2; do
  sh -c 'while :; do :; done' &
  pids+=($!)
done
trap 'kill "${pids[@]}" 2>/dev/null || true' EXIT
"$@"
