#!/usr/bin/env bash
# Regenerate deploy/requirements-board.txt: the runtime set (pyproject's dependencies, no extras)
# resolved for an aarch64 board (CPython 3.11, glibc >= 2.28), every version pinned to
# constraints.txt and every file hashed, so `pip install --require-hashes` on the board installs
# exactly what CI tested. Wheels only: a board must never compile numpy or OpenCV.
# The same lock serves the amd64 container: this script fails if an x86-64 resolution differs.
# Needs network access to PyPI. Uses `uv` from PATH, or installs uv $UV_VERSION into a temp venv.
set -euo pipefail
cd "$(dirname "$0")/.."
UV_VERSION="${UV_VERSION:-0.13.9}"
out=deploy/requirements-board.txt
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

uv="$(command -v uv || true)"
if [ -z "$uv" ]; then
    python3 -m venv "$tmp/uv-venv"
    "$tmp/uv-venv/bin/python" -m pip install --quiet "uv==$UV_VERSION"
    uv="$tmp/uv-venv/bin/uv"
fi

compile() {  # compile PLATFORM OUTPUT
    "$uv" pip compile pyproject.toml \
        --constraints constraints.txt \
        --python-version 3.11 --python-platform "$1" \
        --only-binary :all: --generate-hashes \
        --custom-compile-command deploy/lock.sh \
        --quiet --output-file "$2"
}

compile aarch64-manylinux_2_28 "$tmp/board.txt"
compile x86_64-manylinux_2_28 "$tmp/amd64.txt"
pins() { grep -E '^[A-Za-z0-9._-]+==' "$1" | cut -d' ' -f1; }
if ! diff <(pins "$tmp/board.txt") <(pins "$tmp/amd64.txt") >&2; then
    echo "lock.sh: the x86-64 resolution differs from the aarch64 one (above); the container needs its own lock" >&2
    exit 1
fi
mv "$tmp/board.txt" "$out"
echo "wrote $out ($(pins "$out" | wc -l) packages)"
