#!/usr/bin/env bash
# Set up the environment on a fresh machine and run the whole test suite (slow tests included).
# Tests that need the real data sets ($AEFABMAP_DATA, see docs/data.md) skip when they are absent.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(scripts/setup_env.sh full | tail -n 1)"
exec "$venv/bin/python" -m pytest -ra "$@"
