"""Flat vocabulary for binary descriptors at int8 cost, with exactly the words of the float search.

A binary descriptor's bits x in {0, 1}^D go to the centroid c_k in [0, 1]^D (the mean of its
cluster's bits) nearest in squared L2, i.e. the k maximising S_k = x.c_k - |c_k|^2 / 2. The
float search (NearestCentroidQuantizer) computes every x.c_k with a float32 product, the
largest cost of a frame. Here the centroids are stored as int8, q_k = round(127 (2 c_k - 1)),
and onnxruntime's int8 product gives the integers Y_k = x.q_k. Since c_k = (q_k / 127 + 1) / 2
+ e_k with a known residual e_k,

    254 S_k - 127 |x| = z_k + delta_k,   z_k = Y_k - round(127 |c_k|^2),
    delta_k = 254 x.e_k - (127 |c_k|^2 - round(127 |c_k|^2)).

x holds only 0s and 1s, so 254 x.e_k lies between 254 times the sum of e_k's negative entries
and 254 times the sum of its positive ones: delta_k lies in an interval [lo_k, hi_k] known per
word (the norm term's rounding is known exactly). The best word b has z_b + hi_b >= 254 S_b -
127 |x| >= 254 S_j - 127 |x| >= z_j + lo_j for every j, so it lies among the k with

    z_k + hi_k >= max_j (z_j + lo_j)

Rows with one such candidate take it; the others are re-ranked with exact float64 products.
The result is the exact arg-min (ties to the lowest id), whatever the centroids; centroids far
from [0, 1] only widen the intervals and cost time (`flat_quantizer` then keeps the float search).
Bounds per word, rather than one band of the worst word's width, halve the rows re-ranked
(CHANGELOG.md, "The AE's arg-max in blocks; the flat int8 search's intervals").

The int8 product cannot saturate on x86 without VNNI (pairs of products are summed in int16):
one operand is 0 or 1, so a pair sums to at most 2 * 127.
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.kernels import compiled, native
from aefabmap_runtime.core.words.onnx_matmul import INPUT_NAME, OUTPUT_NAME, matmul_integer_model
from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer, check_vectors

_LEVELS = 127  # int8 steps on each side of 1/2
#: Bytes of int32 products per int8 product call. The selection then reads the block while it is
#: still in cache: on a Zen 4 core (1 MiB L2) 128-row chunks were faster than 512 rows and than
#: 32 rows (docs/results.md, "Quantiser").
BLOCK_BYTES = 2 << 20
_SAFETY = 1.0  # z units (1/254 of a score unit) around each word's interval: float64 rounding


def flat_quantizer(centroids: np.ndarray, distance: str, float32: bool = False, threads: int = 1):
    """The flat search of a vocabulary (Quantizer protocol), trainer and runtime alike.

    centroids (K, D) float32; distance: the feature kind's ("hamming" for binary kinds). A binary
    kind whose centroids lie in [0, 1] (means of bits, as k-means leaves them) gets the int8
    search; any other, or float32=True, the float32 product. Both give the arg-min of squared L2.
    """
    c = np.asarray(centroids, dtype=np.float32)
    if not float32 and distance == "hamming" and c.size and c.min() >= 0 and c.max() <= 1:
        return BitCentroidQuantizer(c, threads=threads)
    return NearestCentroidQuantizer(c)


def product_chunk(words: int) -> int:
    """Descriptors per int8 product call for a vocabulary of `words`: the largest power of two
    in [64, 512] whose int32 block of products (chunk x words x 4 bytes) fits in BLOCK_BYTES."""
    fit = BLOCK_BYTES // (4 * max(1, words))
    return int(min(512, max(64, 1 << max(0, fit.bit_length() - 1))))


class BitCentroidQuantizer:
    """Nearest mean centroid of bit vectors (Quantizer protocol), via an int8 product.

    centroids: (K, D) float32, D a multiple of 8 (the unpacked bits of D / 8 bytes).
    threads: onnxruntime intra-op threads. chunk: descriptors per int8 product; None: the largest
    power of two (64 to 512) whose (chunk, K) int32 block of products fits in `BLOCK_BYTES`.
    """

    accepts_packed_bits = True

    def __init__(self, centroids: np.ndarray, threads: int = 1, chunk: int | None = None) -> None:
        c = np.asarray(centroids, dtype=np.float32)
        if c.ndim != 2 or c.shape[0] < 1 or c.shape[1] < 8 or c.shape[1] % 8:
            raise InputError(f"bit centroids must be a non-empty (K, D) array with D a multiple of 8, got {c.shape}")
        if not np.isfinite(c).all():
            raise InputError("bit centroids hold NaN or infinite values")
        # onnxruntime here, not at the top: a bundle searched by the float product (flat_quantizer)
        # never builds a graph, and importing onnxruntime alone costs resident memory on a board.
        import onnxruntime as ort

        from aefabmap_runtime.core.words.onnx_quantizer import session_options

        opts = session_options(threads)
        self.centroids = np.ascontiguousarray(c)
        self._float = NearestCentroidQuantizer(self.centroids)
        self.vocabulary_size, self.descriptor_length = (int(n) for n in c.shape)
        self._chunk = int(chunk) if chunk is not None else product_chunk(self.vocabulary_size)
        c64 = c.astype(np.float64)
        q = np.clip(np.rint(_LEVELS * (2.0 * c64 - 1.0)), -_LEVELS, _LEVELS)
        residual = c64 - (q / _LEVELS + 1.0) / 2.0
        sq_norms = np.einsum("kd,kd->k", c64, c64)
        norm_term = np.rint(_LEVELS * sq_norms)
        norm_rounding = _LEVELS * sq_norms - norm_term
        # Each word's interval [lo, hi] of delta (module doc), widened to whole z units.
        hi = np.ceil(2 * _LEVELS * np.clip(residual, 0.0, None).sum(axis=1) - norm_rounding + _SAFETY)
        lo = np.floor(2 * _LEVELS * np.clip(residual, None, 0.0).sum(axis=1) - norm_rounding - _SAFETY)
        #: z_k + hi_k as an offset of the product Y_k, and the interval widths hi_k - lo_k (int32).
        self._upper_offset = (hi - norm_term).astype(np.int32)
        self._width = (hi - lo).astype(np.int32)
        self._half_sq_norms = 0.5 * sq_norms
        self._session = ort.InferenceSession(
            matmul_integer_model(q.astype(np.int8).T), sess_options=opts, providers=["CPUExecutionProvider"]
        )
        compiled.prepare(select_kernel)

    def quantize(self, vectors: np.ndarray) -> np.ndarray:
        """Word ids (N,) int32 of descriptor vectors (N, D): bit vectors (0 or 1) by the int8
        search; any other values by the float32 product (the same arg-min, at float cost)."""
        x = check_vectors(vectors, self.descriptor_length)
        bits = x.astype(np.uint8)
        if not np.array_equal(bits, x) or (bits.size and bits.max() > 1):
            return self._float.quantize(x)
        return self._search(bits)

    def quantize_raw(self, packed: np.ndarray) -> np.ndarray:
        """Word ids (N,) int32 of packed descriptors (N, D / 8) uint8."""
        packed = np.asarray(packed)
        if packed.ndim != 2 or packed.dtype != np.uint8 or packed.shape[1] * 8 != self.descriptor_length:
            raise InputError(f"packed descriptors must be uint8 (N, {self.descriptor_length // 8}), got "
                             f"{packed.dtype} {packed.shape}")
        return self._search(np.unpackbits(packed, axis=1))

    def _search(self, bits: np.ndarray) -> np.ndarray:
        out = np.empty(bits.shape[0], np.int32)
        for s in range(0, bits.shape[0], self._chunk):
            out[s : s + self._chunk] = self._search_chunk(bits[s : s + self._chunk])
        return out

    def _search_chunk(self, bits: np.ndarray) -> np.ndarray:
        products = self._session.run([OUTPUT_NAME], {INPUT_NAME: bits})[0]
        if compiled.active() == "compiled":
            best = np.empty(bits.shape[0], np.int32)
            select_kernel()(products, self._upper_offset, self._width, bits, self.centroids, self._half_sq_norms, best)
            return best
        return self._select(products, bits)

    def _select(self, upper: np.ndarray, bits: np.ndarray) -> np.ndarray:
        """numpy path of `select_kernel`: upper (n, K) int32 products, overwritten with z + hi."""
        upper += self._upper_offset
        floor = (upper - self._width).max(axis=1)  # max_j (z_j + lo_j) of each row
        candidate = upper >= floor[:, None]
        best = np.argmax(candidate, axis=1)  # the only candidate where there is one
        ambiguous = np.flatnonzero(candidate.sum(axis=1) > 1)
        if ambiguous.size:
            rows, words = np.nonzero(candidate[ambiguous])
            # Exact scores of the candidates (row-major: words ascending within each row).
            exact = np.einsum("pd,pd->p", bits[ambiguous[rows]].astype(np.float64),
                              self.centroids[words].astype(np.float64))
            exact -= self._half_sq_norms[words]
            starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
            row_max = np.repeat(np.maximum.reduceat(exact, starts), np.diff(np.r_[starts, rows.size]))
            # Each row's first exact maximum: the lowest id among ties, as the float search.
            winners = np.flatnonzero(exact >= row_max)
            row_of, first = np.unique(rows[winners], return_index=True)
            best[ambiguous[row_of]] = words[winners[first]]
        return best.astype(np.int32)


@compiled.kernel(native.select_words)
def select_kernel():
    """Per row of int8 products (overwritten with z + hi): the candidates (module doc), and the
    exact re-rank where there is more than one; compiled (runtime/aefabmap_runtime/core/kernels/compiled.py). The rows'
    two passes come first and the re-ranks after, in a second loop: kept apart, both passes
    vectorise (together they ran slower; docs/results.md, "Quantiser")."""
    def select(products, upper_offset, width, bits, centroids, half_sq_norms, best):
        n, k = products.shape
        d = bits.shape[1]
        floors = np.empty(n, np.int32)
        for i in range(n):
            upper = products[i]
            floor = np.int32(-(2**31 - 1))
            for j in range(k):  # z + hi in place and the largest z + lo: branch-free, vectorised
                upper[j] += upper_offset[j]
                floor = max(floor, upper[j] - width[j])
            # Candidates and the sum of their ids, branch-free: with one candidate (most rows),
            # that sum is the word.
            count, where = 0, 0
            for j in range(k):
                inside = upper[j] >= floor
                count += inside
                where += j * inside
            best[i] = where if count == 1 else -1
            floors[i] = floor
        for i in range(n):
            if best[i] >= 0:
                continue
            top_exact, arg = -np.inf, 0
            upper, floor, x = products[i], floors[i], bits[i]
            for j in range(k):
                if upper[j] >= floor:
                    c = centroids[j]
                    s = 0.0  # float64 sum of float32 centroid values, in bit order
                    for t in range(d):  # branch-free: a clear bit adds an exact 0.0
                        s += np.float64(c[t]) * x[t]
                    s -= half_sq_norms[j]
                    if s > top_exact:
                        top_exact, arg = s, j
            best[i] = arg

    return compiled.numba.njit(
        "void(int32[:, ::1], int32[::1], int32[::1], uint8[:, ::1], float32[:, ::1], float64[::1], int32[::1])",
        nogil=True, cache=False, boundscheck=False)(select)
