"""Packed binary descriptors: popcount and Hamming distance (the one place both live).

Used by the vocabulary tree's descent, the inverted index's routing, matching in verification
(same-word pairs and the all-pairs nearest neighbours of the brute-force retry) and the SLAM
odometry's matching.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.kernels import compiled, native

#: Bits set in each byte value: the popcount table when numpy has no bitwise_count (< 2.0).
POPCOUNT_TABLE = np.array([i.bit_count() for i in range(256)], np.uint8)
_HAS_BITWISE_COUNT = hasattr(np, "bitwise_count")


def popcount_rows(x: np.ndarray, use_table: bool = False) -> np.ndarray:
    """Bits set along the last axis of a uint8 array (..., W) -> (...,) int32.

    np.bitwise_count (numpy >= 2) on 64-bit words when W % 8 == 0, else on bytes; use_table
    (or numpy < 2): the 256-entry table. The last axis is summed by adding its columns: numpy's
    reduction over a short last axis costs more than the popcount itself, and a table gather
    summed along the bytes costs far more (docs/results.md, "Per frame").
    """
    if x.dtype != np.uint8:
        raise InputError(f"popcount_rows needs uint8 bytes, got {x.dtype}")
    if use_table or not _HAS_BITWISE_COUNT:
        bits = POPCOUNT_TABLE[x]
    else:
        if x.shape[-1] % 8 == 0:
            x = np.ascontiguousarray(x).view(np.uint64)
        bits = np.bitwise_count(x)
    acc = bits[..., 0].astype(np.int32)
    for j in range(1, bits.shape[-1]):
        acc += bits[..., j]
    return acc


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance of packed bit rows, broadcast: a (..., W) uint8, b (..., W) uint8 -> int32."""
    return popcount_rows(np.bitwise_xor(a, b))


@functools.cache
def popcount64_intrinsic():
    """numba's popcount64(x): bits set in a uint64 (the CPU's popcount instruction where it has
    one), for kernels built while numba is in use (it imports numba)."""
    from numba import types
    from numba.extending import intrinsic

    @intrinsic
    def popcount64(typingctx, x):
        def codegen(context, builder, signature, args):
            return builder.ctpop(args[0])

        return types.uint64(types.uint64), codegen

    return popcount64


@compiled.kernel(native.nearest_two)
def nearest_two_kernel():
    """Two nearest rows by Hamming distance over uint64 words, compiled (runtime/aefabmap_runtime/core/kernels/compiled.py).

    a (N, W) holds the query rows; bt (W, M) the searched rows transposed, one array per 64-bit
    word, so that the loop over rows reads each word array in sequence and compiles to vector
    popcounts (the row-major (M, W) layout read 4 words per row with strides: several times
    slower; docs/results.md, "Per frame"). Each row's distance d and index j are packed into one
    key d * 2^32 + j, so the nearest is a branch-free minimum and a tie goes to the lower index
    (as in OpenCV's batchDistance); the second nearest is the minimum once the first's key is masked. (A scan
    that tracked the two smallest with branches took longer than the distances themselves.)
    """
    popcount64 = popcount64_intrinsic()

    def nearest_two(a, bt, dist, index):
        n, w = a.shape
        m = bt.shape[1]
        none = np.int64(1) << 62
        key = np.empty(m, np.int64)
        for i in range(n):
            best = none
            if w == 4:  # ORB's 256 bits: unrolled
                a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
                b0, b1, b2, b3 = bt[0], bt[1], bt[2], bt[3]
                for j in range(m):
                    d = np.int64(popcount64(a0 ^ b0[j]) + popcount64(a1 ^ b1[j])
                                 + popcount64(a2 ^ b2[j]) + popcount64(a3 ^ b3[j]))
                    key[j] = (d << 32) | j
                    best = min(best, key[j])
            else:
                key[:] = 0
                for k in range(w):
                    ak, bk = a[i, k], bt[k]
                    for j in range(m):
                        key[j] += np.int64(popcount64(ak ^ bk[j]))
                for j in range(m):
                    key[j] = (key[j] << 32) | j
                    best = min(best, key[j])
            key[best & 0xFFFFFFFF] = none
            second = none
            for j in range(m):
                second = min(second, key[j])
            dist[i, 0], index[i, 0] = best >> 32, best & 0xFFFFFFFF
            if second != none:
                dist[i, 1], index[i, 1] = second >> 32, second & 0xFFFFFFFF

    return compiled.numba.njit("void(uint64[:, ::1], uint64[:, ::1], int32[:, ::1], int32[:, ::1])",
                               nogil=True, cache=False, boundscheck=False)(nearest_two)


def packed_words(rows: np.ndarray) -> np.ndarray:
    """Packed bit rows (N, B) uint8 as C-contiguous (N, ceil(B / 8)) uint64 words, zero-padded
    (zero bytes xor to zero: whole words change no Hamming distance), for the compiled kernels."""
    rows = np.ascontiguousarray(rows, np.uint8)
    pad = -rows.shape[1] % 8
    return (np.pad(rows, ((0, 0), (0, pad))) if pad else rows).view(np.uint64)


#: Distance reported for a missing neighbour (fewer than two rows to search): larger than any
#: Hamming distance of a descriptor under 2^28 bytes.
_FAR = np.int32(2**31 - 1)


def nearest_two(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each packed bit row of a (N, W) uint8, its two nearest rows of b (M, W) uint8 by Hamming
    distance -> (distance (N, 2) int32, index (N, 2) int32), nearest first; a tie goes to the
    lower index. Where b has fewer than two rows the missing neighbour has index -1 and
    distance 2^31 - 1.

    Compiled kernel when in use (runtime/aefabmap_runtime/core/kernels/compiled.py), else OpenCV's batchDistance: the same
    distances and indices; the kernel is much faster (docs/results.md, "Per frame").
    """
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    if a.dtype != np.uint8 or b.dtype != np.uint8 or a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise InputError(f"nearest_two needs uint8 rows of one width, got {a.dtype}{a.shape} and {b.dtype}{b.shape}")
    n, m = a.shape[0], b.shape[0]
    dist = np.full((n, 2), _FAR, np.int32)
    index = np.full((n, 2), -1, np.int32)
    if n == 0 or m == 0:
        return dist, index
    if compiled.active() == "compiled":
        nearest_two_kernel()(packed_words(a), np.ascontiguousarray(packed_words(b).T), dist, index)
        return dist, index
    k = min(2, m)
    d, i = cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=k)
    dist[:, :k], index[:, :k] = d, i
    return dist, index
