#!/usr/bin/env bash
# Build the compiled kernels (runtime/aefabmap_runtime/core/kernels/kernels.c) for aarch64 and run the tests that
# compare them with the numpy / OpenCV fallbacks under qemu user-mode emulation, with the board's
# numpy and OpenCV wheels (deploy/requirements-board.txt), from a Debian 12 (bookworm) amd64
# machine, as root.
#
#   deploy/check_aarch64.sh [WORKDIR]          default WORKDIR: /tmp/aefabmap-aarch64
#   deploy/check_aarch64.sh WORKDIR BUNDLE IMAGES GT EXCLUDE
#
# With a bundle and a sequence it also runs `aefabmap eval` there on this machine (the project's
# .venv, or $AEFABMAP_PYTHON) and emulated, and fails unless every frame's decisions are the same:
# keypoints, words, FAB-MAP's scores, the candidates checked, the verified place. The board then
# decides as the machine its settings were measured on (docs/results.md, "The board's arithmetic").
#
# Debian's arm64 python3.11 is unpacked into WORKDIR/sysroot, not installed: apt would replace
# the machine's amd64 python3 with the arm64 one. Writes runtime/aefabmap_runtime/core/kernels/
# _kernels.cpython-311-aarch64-linux-gnu.so into this checkout (git-ignored; the x86-64 library beside it is untouched).
# Emulated timings mean nothing: this checks results only.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
WORK=${1:-/tmp/aefabmap-aarch64}
[ $# -le 1 ] || [ $# -eq 5 ] || { sed -n 2,17p "$0" >&2; exit 2; }
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
# fetch DIR PACKAGE...: PyPI's wheels of the packages for CPython 3.11 on aarch64 (or pure Python)
# into DIR, unpacked into $WORK/site.
fetch() {
    local dir=$1; shift
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.11 --implementation cp \
        --abi cp311 --abi abi3 --abi none --platform manylinux_2_28_aarch64 --platform manylinux2014_aarch64 \
        --platform any -d "$dir" "$@"
    for whl in "$dir"/*.whl; do python3 -m zipfile -e "$whl" "$WORK/site"; done
}
CFLAGS="$(var CFLAGS) $(var CCSHARED)"
LDFLAGS=$(var LDSHARED | cut -d' ' -f2-)
OUT=$REPO/runtime/aefabmap_runtime/core/kernels/_kernels$(var EXT_SUFFIX)
cd "$REPO"
set -x
aarch64-linux-gnu-gcc $CFLAGS -c runtime/aefabmap_runtime/core/kernels/kernels.c -o "$WORK/kernels.o" -O3 -ffp-contract=off
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
fetch "$WORK/wheels" $pins pytest pytest-timeout iniconfig packaging pluggy pygments
mkdir -p "$WORK/bin" && ln -sf "$(command -v aarch64-linux-gnu-gcc)" "$WORK/bin/cc"  # test_native builds a stub library
PATH=$WORK/bin:$PATH PYTHONPATH=$WORK/site:$REPO/runtime AEFABMAP_DATA=/nonexistent QEMU_CPU=cortex-a53 "${PY[@]}" \
    -m pytest -p no:cacheprovider -q -rs tests/runtime/core/kernels/test_{native,bits}.py \
    tests/runtime/core/rank/test_{scatter,postings,fabmap}.py tests/runtime/core/decide/test_candidate_policy.py \
    tests/runtime/core/verify/test_{model_errors,word_matches,nearest,geometry_acceptance}.py \
    tests/runtime/core/features/test_{learned_description,orb_description}.py
#    The learned descriptor's kernel again on a Cortex-A76 (Raspberry Pi 5, ARMv8.2 with dot products).
PYTHONPATH=$WORK/site:$REPO/runtime AEFABMAP_DATA=/nonexistent QEMU_CPU=cortex-a76 "${PY[@]}" \
    -m pytest -p no:cacheprovider -q -rs tests/runtime/core/features/test_learned_description.py -k compiled
echo "aarch64 kernels check passed: $OUT"
[ $# -eq 5 ] || exit 0

# 5. The same eval here and emulated. The rest of the board's lock, but onnxruntime 1.20 (the
#    runtime set's floor), whose import does not crash under qemu-user; its int8 products are integers.
BUNDLE=$(realpath "$2"); IMAGES=$(realpath "$3"); GT=$(realpath "$4"); EXCLUDE=$5
HOST_PY=${AEFABMAP_PYTHON:-$REPO/.venv/bin/python}
pins=$(grep -oE '^[A-Za-z0-9_.-]+==[^ ]+' deploy/requirements-board.txt | grep -vE '^(onnxruntime|numpy|opencv-python-headless)==')
fetch "$WORK/wheels-eval" $pins onnxruntime==1.20.1 coloredlogs humanfriendly sympy mpmath  # numpy, OpenCV: step 4
EVAL=(-m aefabmap eval --model "$BUNDLE" --images "$IMAGES" --gt "$GT" --exclude "$EXCLUDE" --fabmap-score llr --no-progress)
"$HOST_PY" "${EVAL[@]}" --frames "$WORK/here.frames.jsonl" | tail -3
PYTHONPATH=$WORK/site:$REPO:$REPO/runtime QEMU_CPU=cortex-a53 "${PY[@]}" "${EVAL[@]}" --frames "$WORK/board.frames.jsonl" | tail -3
python3 - "$WORK/here.frames.jsonl" "$WORK/board.frames.jsonl" <<'EOF'
import json, sys
# The geometric fits' diagnostics (OpenCV's MAGSAC in floating point) and the last digits of
# scores (libm) may differ between CPUs; what a robot receives may not.
FIT = {"nfa", "inliers", "matches", "geometry_model", "model"}
def decisions(value):
    if isinstance(value, dict):
        return {k: decisions(v) for k, v in value.items() if k not in FIT}
    if isinstance(value, list):
        return [decisions(v) for v in value]
    return float(f"{value:.12g}") if isinstance(value, float) else value
here, board = ([json.loads(line) for line in open(p)] for p in sys.argv[1:3])
differ = [a["frame"] for a, b in zip(here, board) if decisions(a) != decisions(b)]
print(f"{len(here)} frames: equal in every field {sum(a == b for a, b in zip(here, board))}, "
      f"the same decisions {len(here) - len(differ)}" + (f"; they differ at frames {differ[:10]}" if differ else ""))
sys.exit(1 if differ or len(here) != len(board) else 0)
EOF
echo "aarch64 eval check passed"
