"""The ahead-of-time compiled kernels (runtime/aefabmap_runtime/core/kernels/kernels.c), loaded with ctypes.

The library is built when the package is installed (pyproject.toml, `ext-modules`; optional: an
install without a C compiler still succeeds and runs the numpy / OpenCV fallbacks). It holds plain
machine code, nothing is generated at run time, so it runs under MemoryDenyWriteExecute=yes, where
numba's JIT cannot (runtime/aefabmap_runtime/core/kernels/compiled.py chooses between them).

Each function here takes the arrays the numba kernel of the same job takes, checks their dtype,
layout and shape (the C code trusts them: a wrong array would be read out of bounds), and passes
their data addresses with the shapes.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import ConfigError

#: The interface version kernels.c reports (aefabmap_kernels_version): a library built from other
#: sources is not used.
VERSION = 7

_P = ctypes.c_void_p
_I64 = ctypes.c_int64
_SIGNATURES = {
    "aefabmap_kernels_version": (_I64, []),
    "scatter_buffers": (None, [_P, _P, _P, _P, _I64]),
    "append_postings": (None, [_P, _P, ctypes.c_int32, _I64]),
    "nearest_two": (ctypes.c_int, [_P, _P, _P, _P, _I64, _I64, _I64]),
    "same_word": (_I64, [_P, _P, _P, _P, _P, ctypes.c_float, ctypes.c_float, _P, _I64, _I64, _I64]),
    "distinct": (ctypes.c_int, [_P, _P, ctypes.c_double, ctypes.c_double, _P, _P, _I64]),
    "transfer_errors": (None, [_P, _P, _P, _P, _P, _I64]),
    "epipolar_errors": (None, [_P, _P, _P, ctypes.c_double, _P, _I64]),
    "select_words": (ctypes.c_int, [_P, _P, _P, _P, _P, _P, _P, _I64, _I64, _I64]),
    "orb_describe": (_I64, [_P, _P, _P, _P, _I64, _P, _P, _P, _P, _P, _I64, _P, _I64, _P, _P]),
    "orb_keypoints": (_I64, [_P, _P, _P, _P, _I64, _I64, _I64, _I64, _P, _I64, _P, _I64, _P, _P, _P, _P, _P, _I64]),
    "resize_levels": (_I64, [_P, _P, _P, _P, _I64]),
    "learned_describe": (_I64, [_P, _P, _P, _P, _I64, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _I64, _P, _P, _P, _I64, _P,
                                _I64]),
}


def library_paths() -> list[Path]:
    """Where the built library may be: `_kernels` plus an extension suffix of this interpreter,
    next to this module."""
    here = Path(__file__).resolve().parent
    return [here / f"_kernels{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES]


def _load() -> tuple[ctypes.CDLL | None, str]:
    found = [p for p in library_paths() if p.is_file()]
    if not found:
        return None, "the compiled kernels were not built (no C compiler at install?)"
    try:
        lib = ctypes.CDLL(str(found[0]))
        for name, (restype, argtypes) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
    except (OSError, AttributeError) as exc:
        return None, f"the compiled kernels cannot be loaded: {exc}"
    if lib.aefabmap_kernels_version() != VERSION:
        return None, f"the compiled kernels at {found[0]} are from another version: reinstall aefabmap"
    return lib, ""


_lib, _unavailable = _load()


def available() -> bool:
    """True when the library is built and loads here."""
    return _lib is not None


def unavailable_reason() -> str:
    """Why the library cannot be used ("" when it can)."""
    return _unavailable


def _arg(a: np.ndarray, dtype, ndim: int) -> int:
    """The data address of a C-contiguous array of this dtype and rank (else ConfigError)."""
    if not isinstance(a, np.ndarray) or a.dtype != dtype or a.ndim != ndim or not a.flags.c_contiguous:
        got = f"{a.dtype}{a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        raise ConfigError(f"compiled kernel argument: expected C-contiguous {np.dtype(dtype)} of rank {ndim}, got {got}")
    return a.__array_interface__["data"][0]  # a little cheaper than a.ctypes.data


def _writable(a: np.ndarray, dtype, ndim: int) -> int:
    if isinstance(a, np.ndarray) and not a.flags.writeable:
        raise ConfigError("compiled kernel output array is read-only")
    return _arg(a, dtype, ndim)


def _same(n: int, *sizes: int) -> None:
    if any(s != n for s in sizes):
        raise ConfigError(f"compiled kernel arguments of unequal lengths: {(n, *sizes)}")


def _memory(status: int) -> None:
    if status < 0:
        raise MemoryError("compiled kernel: out of memory")


def scatter_buffers(acc, addresses, weights, lens) -> None:
    """As scatter.buffers_kernel: acc[row ids] += weight, row i at data address addresses[i]."""
    _same(addresses.size, weights.size, lens.size)
    _lib.scatter_buffers(_writable(acc, np.float64, 1), _arg(addresses, np.intp, 1), _arg(weights, np.float64, 1),
                         _arg(lens, np.int32, 1), addresses.size)


def append_postings(addresses, positions, pid) -> None:
    """As scatter.append_kernel: buffer i (int32 data at addresses[i]) gets pid at positions[i]."""
    _same(addresses.size, positions.size)
    _lib.append_postings(_arg(addresses, np.intp, 1), _arg(positions, np.int32, 1), int(pid), addresses.size)


def nearest_two(a, bt, dist, index) -> None:
    """As bits.nearest_two_kernel: a (N, W) uint64, bt (W, M) uint64, dist and index (N, 2) int32."""
    n, w = a.shape
    if bt.shape[0] != w or dist.shape != (n, 2) or index.shape != (n, 2):
        raise ConfigError(f"nearest_two: shapes {a.shape}, {bt.shape}, {dist.shape}, {index.shape} do not agree")
    _memory(_lib.nearest_two(_arg(a, np.uint64, 2), _arg(bt, np.uint64, 2), _writable(dist, np.int32, 2),
                             _writable(index, np.int32, 2), n, w, bt.shape[1]))


def same_word(qw, qd, pw, order, pd, cap, ratio, out) -> int:
    """As word_matches.same_word_kernel; returns the number of matches written to out."""
    n, w = qd.shape
    m = pd.shape[0]
    _same(n, qw.size)
    _same(m, pw.size, order.size)
    if pd.shape[1] != w or out.shape != (min(n, m), 2):
        raise ConfigError(f"same_word: shapes {qd.shape}, {pd.shape}, {out.shape} do not agree")
    if m and (order.min() < 0 or order.max() >= m):
        raise ConfigError("same_word: order holds an index outside the place rows")
    count = _lib.same_word(_arg(qw, np.int64, 1), _arg(qd, np.uint64, 2), _arg(pw, np.int64, 1),
                           _arg(order, np.int64, 1), _arg(pd, np.uint64, 2), float(cap), float(ratio),
                           _writable(out, np.int64, 2), n, w, m)
    _memory(count)
    return count


def distinct(xq, xp, radius_q, radius_p, offsets, keep) -> None:
    """As verification.distinct_kernel: keep (K,) bool cleared where an earlier match shares a cell."""
    k = xq.shape[0]
    if xp.shape != (k, 2) or xq.shape != (k, 2) or offsets.shape != (4, 2) or keep.shape != (k,):
        raise ConfigError(f"distinct: shapes {xq.shape}, {xp.shape}, {offsets.shape}, {keep.shape} do not agree")
    _memory(_lib.distinct(_arg(xq, np.float64, 2), _arg(xp, np.float64, 2), float(radius_q), float(radius_p),
                          _arg(offsets, np.float64, 2), _writable(keep, np.bool_, 1), k))


def _points(k: int, *arrays) -> None:
    if any(a.shape != (k, 2) for a in arrays):
        raise ConfigError(f"model errors: point arrays {[a.shape for a in arrays]} are not ({k}, 2)")


def transfer_errors(H, Hi, src, dst, out) -> None:
    """As model_errors.transfer_kernel."""
    k = out.shape[0]
    _points(k, src, dst)
    if H.shape != (3, 3) or Hi.shape != (3, 3):
        raise ConfigError("transfer errors: H and its inverse must be 3x3")
    _lib.transfer_errors(_arg(H, np.float64, 2), _arg(Hi, np.float64, 2), _arg(src, np.float64, 2),
                         _arg(dst, np.float64, 2), _writable(out, np.float64, 1), k)


def epipolar_errors(F, xq, xp, min_normal, out) -> None:
    """As model_errors.epipolar_kernel."""
    k = out.shape[0]
    _points(k, xq, xp)
    if F.shape != (3, 3):
        raise ConfigError("epipolar errors: F must be 3x3")
    _lib.epipolar_errors(_arg(F, np.float64, 2), _arg(xq, np.float64, 2), _arg(xp, np.float64, 2), float(min_normal),
                         _writable(out, np.float64, 1), k)


def select_words(products, upper_offset, width, bits, centroids, half_sq_norms, best) -> None:
    """As bit_centroids.select_kernel."""
    n, k = products.shape
    d = bits.shape[1]
    _same(k, upper_offset.size, width.size, half_sq_norms.size, centroids.shape[0])
    _same(n, bits.shape[0], best.size)
    if centroids.shape[1] != d:
        raise ConfigError(f"select: centroids {centroids.shape} and bits {bits.shape} do not agree")
    _memory(_lib.select_words(_writable(products, np.int32, 2), _arg(upper_offset, np.int32, 1),
                              _arg(width, np.int32, 1), _arg(bits, np.uint8, 2), _arg(centroids, np.float32, 2),
                              _arg(half_sq_norms, np.float64, 1), _writable(best, np.int32, 1), n, k, d))


def orb_describe(levels, inv_scale, x, y, angle, octave, pattern, oriented, upright) -> int:
    """ORB descriptors of keypoints on a blurred pyramid (features/orb_description.py).

    levels: list of (rows, cols) uint8 arrays (rows may be strided); inv_scale (L,) float32; x, y,
    angle (N,) float32; octave (N,) int32 in [0, L); pattern (P, 4) int32; oriented, upright:
    (N, P / 8) uint8 or None. Returns the number of keypoints too near a level's edge to describe
    (their rows are zero)."""
    n, n_levels = x.size, len(levels)
    _same(n, y.size, angle.size, octave.size)
    _same(n_levels, inv_scale.size)
    if pattern.ndim != 2 or pattern.shape[1] != 4 or pattern.shape[0] % 8:
        raise ConfigError(f"orb_describe: pattern {pattern.shape} is not (8k, 4)")
    for out in (oriented, upright):
        if out is not None and out.shape != (n, pattern.shape[0] // 8):
            raise ConfigError(f"orb_describe: output {out.shape} is not ({n}, {pattern.shape[0] // 8})")
    addresses, steps, rows, cols = _level_arrays(levels)
    status = _lib.orb_describe(
        _arg(addresses, np.intp, 1), _arg(steps, np.int64, 1), _arg(rows, np.int64, 1), _arg(cols, np.int64, 1),
        n_levels, _arg(inv_scale, np.float32, 1), _arg(x, np.float32, 1), _arg(y, np.float32, 1),
        _arg(angle, np.float32, 1), _arg(octave, np.int32, 1), n, _arg(pattern, np.int32, 2), pattern.shape[0],
        None if oriented is None else _writable(oriented, np.uint8, 2),
        None if upright is None else _writable(upright, np.uint8, 2))
    if status == -2:
        raise ConfigError("orb_describe: a keypoint's octave lies outside the pyramid")
    _memory(status)
    return int(status)


#: learned_describe's forms, most specialised first: each runs where the CPU has its instructions
#: (x86-64: AVX-512 VNNI, AVX-VNNI, AVX2; aarch64: Advanced SIMD with and without its dot products),
#: else the next one in this order that the CPU runs does.
LEARNED_FORMS = ("avx512-vnni", "avx-vnni", "avx2", "neon-dotprod", "neon", "plain")


def learned_describe(levels, inv_scale, x, y, cosines, sines, octave, grid_u, grid_v, pairs, quads, row_sums,
                     out, form: str = "avx512-vnni") -> None:
    """The learned descriptor of keypoints on a blurred pyramid (features/learned_description.py,
    whose numpy form computes the same bytes).

    levels: list of (rows, cols) uint8 arrays (rows may be strided); inv_scale (L,) float32; x, y,
    cosines, sines (N,) float32; octave (N,) int32 in [0, L); grid_u, grid_v (S,) float32 sample
    offsets, S a multiple of 4; the weights (B, S) int8 twice: pairs (S / 2, B, 2) int16 (pairs[k, b, t]
    = w[b, 2 k + t]) and quads (S / 4, B, 4) int8 (quads[k, b, t] = w[b, 4 k + t]); row_sums (B,)
    int64; out (N, B / 8) uint8. form: the most specialised of LEARNED_FORMS used where the CPU
    runs it (every form gives the same bytes; tests compare them)."""
    if form not in LEARNED_FORMS:
        raise ConfigError(f"learned_describe: form {form!r} is not one of {LEARNED_FORMS}")
    n, n_levels = x.size, len(levels)
    _same(n, y.size, cosines.size, sines.size, octave.size)
    _same(n_levels, inv_scale.size)
    samples, bits = grid_u.size, row_sums.size
    _same(samples, grid_v.size)
    if samples % 4 or pairs.shape != (samples // 2, bits, 2) or quads.shape != (samples // 4, bits, 4) \
            or bits % 8 or out.shape != (n, bits // 8):
        raise ConfigError(f"learned_describe: weights {pairs.shape}, {quads.shape} / output {out.shape} do not fit "
                          f"{bits} bits, {samples} samples")
    addresses, steps, rows, cols = _level_arrays(levels)
    status = _lib.learned_describe(
        _arg(addresses, np.intp, 1), _arg(steps, np.int64, 1), _arg(rows, np.int64, 1), _arg(cols, np.int64, 1),
        n_levels, _arg(inv_scale, np.float32, 1), _arg(x, np.float32, 1), _arg(y, np.float32, 1),
        _arg(cosines, np.float32, 1), _arg(sines, np.float32, 1), _arg(octave, np.int32, 1), n,
        _arg(grid_u, np.float32, 1), _arg(grid_v, np.float32, 1), samples, _arg(pairs, np.int16, 3),
        _arg(quads, np.int8, 3), _arg(row_sums, np.int64, 1), bits, _writable(out, np.uint8, 2),
        LEARNED_FORMS.index(form))
    if status == -2:
        raise ConfigError("learned_describe: a keypoint's octave lies outside the pyramid")
    _memory(status)


def _level_arrays(levels) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Addresses, row strides, rows and columns (L,) of a pyramid's uint8 levels (rows may be strided)."""
    if any(not isinstance(lv, np.ndarray) or lv.dtype != np.uint8 or lv.ndim != 2 or lv.strides[1] != 1
           for lv in levels):
        raise ConfigError("compiled kernel: pyramid levels must be 2-D uint8 arrays with contiguous rows")
    return (np.array([lv.__array_interface__["data"][0] for lv in levels], np.intp),
            np.array([lv.strides[0] for lv in levels], np.int64),
            np.array([lv.shape[0] for lv in levels], np.int64),
            np.array([lv.shape[1] for lv in levels], np.int64))


def resize_levels(levels) -> None:
    """Fill levels[1:] (uint8, rows may be strided, sizes set by the caller), each from the one
    before, by OpenCV's bit-exact bilinear resize (cv2.INTER_LINEAR_EXACT); levels[0] is read only."""
    if len(levels) < 2:
        return
    if any(not lv.flags.writeable for lv in levels[1:]):
        raise ConfigError("resize_levels: an output level is read-only")
    addresses, steps, rows, cols = _level_arrays(levels)
    if np.any(rows < 1) or np.any(cols < 1):
        raise ConfigError("resize_levels: a level has no pixel")
    _memory(_lib.resize_levels(_arg(addresses, np.intp, 1), _arg(steps, np.int64, 1), _arg(rows, np.int64, 1),
                               _arg(cols, np.int64, 1), len(levels)))


def orb_keypoints(levels, crop: int, edge: int, threshold: int, budgets, half_patch: int, umax, portable: bool = False):
    """cv2.ORB's keypoints (Harris score) of a pyramid, each level searched as a one-level cv2.ORB
    searches its crop (features/orb_levels.py). levels: list of (rows, cols) uint8 arrays; crop:
    pixels left out at each edge; edge: the crop's edge threshold; budgets (L,) keypoints per
    level; umax (half_patch + 1,) int32 half-widths of the orientation disc; portable: FAST's
    portable form even where the CPU runs its AVX-512 form (the same keypoints; for tests).

    Returns x, y (N,) int32 level pixels, response, angle (N,) float32 and level (N,) int32."""
    addresses, steps, rows, cols = _level_arrays(levels)
    budgets = np.ascontiguousarray(budgets, np.int64)
    umax = np.ascontiguousarray(umax, np.int32)
    _same(len(levels), budgets.size)
    # A kept keypoint lies `edge` pixels inside the crop: its Harris window (4 pixels) and its
    # orientation disc (half_patch) must lie inside the level.
    if half_patch < 1 or umax.size < half_patch + 1 or crop < 0 or edge < 4 or crop + edge < half_patch \
            or np.any(umax[: half_patch + 1] > half_patch) or np.any(umax < 0):
        raise ConfigError("orb_keypoints: half_patch, umax, crop or edge out of range")
    # FAST keeps at most one corner of any 2 x 2 pixels (a kept one exceeds its neighbours).
    capacity = int(sum(max(0, r - 2 * crop) * max(0, c - 2 * crop) for r, c in zip(rows, cols)) // 4 + 1)
    x, y, level = (np.empty(capacity, np.int32) for _ in range(3))
    response, angle = np.empty(capacity, np.float32), np.empty(capacity, np.float32)
    n = _lib.orb_keypoints(
        _arg(addresses, np.intp, 1), _arg(steps, np.int64, 1), _arg(rows, np.int64, 1), _arg(cols, np.int64, 1),
        len(levels), int(crop), int(edge), int(threshold), _arg(budgets, np.int64, 1), int(half_patch),
        _arg(umax, np.int32, 1), capacity, _writable(x, np.int32, 1), _writable(y, np.int32, 1),
        _writable(response, np.float32, 1), _writable(angle, np.float32, 1), _writable(level, np.int32, 1),
        int(bool(portable)))
    if n == -3:
        raise ConfigError("orb_keypoints: more keypoints than the output holds")
    if n == -2:
        raise ConfigError("orb_keypoints: edge, crop or the orientation disc would read outside a level")
    _memory(n)
    return x[:n], y[:n], response[:n], angle[:n], level[:n]
