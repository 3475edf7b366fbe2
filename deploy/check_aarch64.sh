#!/usr/bin/env bash
# Build the compiled kernels (runtime/core/native/kernels.c) for aarch64 and run the tests that
# compare them with the numpy / OpenCV fallbacks under qemu user-mode emulation, with the board's
# numpy and OpenCV wheels (deploy/requirements-board.txt), from a Debian 12 (bookworm) amd64
# machine, as root.
#
#   deploy/check_aarch64.sh [WORKDIR]          default WORKDIR: /tmp/aefabmap-aarch64
#
# Debian's arm64 python3.11 is unpacked into WORKDIR/sysroot, not installed: apt would replace
# the machine's amd64 python3 with the arm64 one. Writes runtime/core/_kernels.cpython-311-
# aarch64-linux-gnu.so into this checkout (git-ignored; the x86-64 library beside it is untouched).
# Emulated timings mean nothing: this checks results only.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
WORK=${1:-/tmp/aefabmap-aarch64}
SYSROOT=$WORK/sysroot
export DEBIAN_FRONTEND=noninteractive

# 1. Cross compiler and emulator; arm64 package lists.
dpkg --add-architecture arm64
apt-get update -q
apt-get install -y -q qemu-user-static gcc-aarch64-linux-gnu python3-pip

# 2. Debian's arm64 python3.11 (+ libstdc++, for PyPI's numpy) and their dependencies, unpacked
#    into $SYSROOT.
mkdir -p "$WORK/debs" "$SYSROOT"
pkgs=$(apt-get install -s python3:arm64 libstdc++6:arm64 | awk '/^Inst / && /\[arm64\]\)/ {print $2}')
(cd "$WORK/debs" && apt-get download $pkgs)
for deb in "$WORK"/debs/*.deb; do dpkg-deb -x "$deb" "$SYSROOT"; done
PY=(qemu-aarch64-static -L "$SYSROOT" "$SYSROOT/usr/bin/python3.11")
"${PY[@]}" -c 'import platform; print("emulated:", platform.machine(), platform.python_version())'

# 3. The library, compiled as setuptools would on the board: the interpreter's CFLAGS and CCSHARED,
#    then setup.py's extra_compile_args; linked with its LDSHARED flags.
grep -q '"-O3", "-ffp-contract=off"' "$REPO/setup.py" || { echo "setup.py's flags changed: update $0" >&2; exit 1; }
var() { "${PY[@]}" -c "import sysconfig; print(sysconfig.get_config_var('$1'))"; }
CFLAGS="$(var CFLAGS) $(var CCSHARED)"
LDFLAGS=$(var LDSHARED | cut -d' ' -f2-)
OUT=$REPO/runtime/core/_kernels$(var EXT_SUFFIX)
cd "$REPO"
set -x
aarch64-linux-gnu-gcc $CFLAGS -c runtime/core/native/kernels.c -o "$WORK/kernels.o" -O3 -ffp-contract=off
aarch64-linux-gnu-gcc $LDFLAGS "$WORK/kernels.o" -o "$OUT"
{ set +x; } 2>/dev/null
# -ffp-contract=off must leave no fused multiply-add (GCC fuses by default on aarch64).
if aarch64-linux-gnu-objdump -d "$OUT" | grep -qE '\s(fmadd|fmsub|fnmadd|fnmsub|fmla|fmls)\s'; then
    echo "fused multiply-add in $OUT" >&2; exit 1
fi

# 4. The board's numpy and OpenCV (PyPI aarch64 wheels) and pytest, unpacked beside the sysroot;
#    then the kernel tests on a Cortex-A53 (Raspberry Pi 3 / Zero 2, ARMv8.0). Not the tests that
#    need onnxruntime: its import crashes under qemu-user (it parses the host's x86 /proc/cpuinfo).
pins=$(grep -oE '^(numpy|opencv-python-headless)==[^ ]+' deploy/requirements-board.txt)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.11 --implementation cp \
    --abi cp311 --abi abi3 --platform manylinux_2_28_aarch64 --platform manylinux2014_aarch64 \
    -d "$WORK/wheels" $pins pytest pytest-timeout iniconfig packaging pluggy pygments
for whl in "$WORK"/wheels/*.whl; do python3 -m zipfile -e "$whl" "$WORK/site"; done
mkdir -p "$WORK/bin" && ln -sf "$(command -v aarch64-linux-gnu-gcc)" "$WORK/bin/cc"  # test_native builds a stub library
PATH=$WORK/bin:$PATH PYTHONPATH=$WORK/site AEFABMAP_DATA=/nonexistent QEMU_CPU=cortex-a53 "${PY[@]}" \
    -m pytest -p no:cacheprovider -q -rs tests/runtime/core/test_{native,model_errors,scatter,postings,fabmap,bits}.py \
    tests/runtime/core/test_{word_matches,nearest,geometry_acceptance,candidate_policy}.py
echo "aarch64 check passed: $OUT"
