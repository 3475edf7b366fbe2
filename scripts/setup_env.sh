#!/usr/bin/env bash
# Create (or reuse) the project virtualenv and install aefabmap into it.
# Usage: scripts/setup_env.sh runtime|full   (runtime: the board set; full: + trainer, tests, slam)
# The venv lives in $AEFABMAP_VENV (default: .venv in the repo); $PYTHON picks the interpreter (>= 3.11).
# Prints the venv path on its last line.
set -euo pipefail
cd "$(dirname "$0")/.."
profile="${1:-full}"
venv="${AEFABMAP_VENV:-.venv}"
py="${PYTHON:-python3}"
# torch comes from the PyTorch CPU wheel index: PyPI's torch wheel for x86-64 pulls several GB of CUDA packages.
torch_index="${AEFABMAP_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}"

if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "aefabmap needs Python >= 3.11; $py is $("$py" -V 2>&1). Set PYTHON=python3.11 (or newer)." >&2
    exit 2
fi
if [ ! -x "$venv/bin/python" ]; then
    "$py" -m venv "$venv"
fi
pip=("$venv/bin/python" -m pip install --quiet)
"${pip[@]}" --upgrade pip
case "$profile" in
    runtime) "${pip[@]}" -c constraints.txt -e . ;;
    full)
        torch_pin="$(grep -E '^torch==' constraints.txt)"
        if ! "$venv/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '${torch_pin#torch==}')" 2>/dev/null; then
            "${pip[@]}" --index-url "$torch_index" "$torch_pin"
        fi
        "${pip[@]}" -c constraints.txt -e ".[train,plot,dev,ros,foxglove,slam,fast]" ;;
    *) echo "usage: $0 runtime|full" >&2; exit 2 ;;
esac
echo "$venv"
