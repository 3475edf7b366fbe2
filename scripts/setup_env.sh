#!/usr/bin/env bash
# Create (or reuse) the project virtualenv and install aefabmap into it.
# Usage: scripts/setup_env.sh runtime|full   (runtime: the board set; full: + trainer + tests)
# The venv lives in $AEFABMAP_VENV (default: .venv in the repo).
set -euo pipefail
cd "$(dirname "$0")/.."
profile="${1:-full}"
venv="${AEFABMAP_VENV:-.venv}"
py="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
    "$py" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --upgrade pip
case "$profile" in
    runtime) "$venv/bin/python" -m pip install --quiet -c constraints.txt -e . ;;
    # torch is pinned to the CPU build in constraints.txt: an unpinned torch pulls a multi-GB CUDA build.
    full) "$venv/bin/python" -m pip install --quiet -c constraints.txt -e ".[train,plot,dev]" ;;
    *) echo "usage: $0 runtime|full" >&2; exit 2 ;;
esac
echo "$venv"
