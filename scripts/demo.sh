#!/usr/bin/env bash
# Set up the runtime environment on a fresh machine and run the main job end to end:
# a publisher process streams camera frames over Zenoh (loopback), the runtime process
# detects loop closures, publishes them and writes an MCAP log, which is then replayed
# offline and checked. Extra arguments go to `aefabmap demo` (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(scripts/setup_env.sh runtime | tail -n 1)"
exec "$venv/bin/aefabmap" demo "$@"
