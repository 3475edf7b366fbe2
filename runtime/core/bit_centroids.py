"""Flat vocabulary for binary descriptors at int8 cost, with exactly the words of the float search.

A binary descriptor's bits x in {0, 1}^D go to the centroid c_k in [0, 1]^D (the mean of its
cluster's bits) nearest in squared L2, i.e. the k maximising S_k = x.c_k - |c_k|^2 / 2. The
float search (NearestCentroidQuantizer) computes every x.c_k with a float32 product, the
largest cost of a frame. Here the centroids are stored as int8, q_k = round(127 (2 c_k - 1)),
and onnxruntime's int8 product gives the integers Y_k = x.q_k. Since c_k = (q_k / 127 + 1) / 2
+ e_k with a known residual e_k,

    254 S_k - 127 |x| = Y_k - round(127 |c_k|^2) + delta_k,   |delta_k| <= beta
    beta = 0.5 + 254 max_k sum_i |e_ki|   (rounding of the norm term; x has no more than D ones)

so the best word lies among the k with z_k = Y_k - round(127 |c_k|^2) >= max_j z_j - 2 beta.
Rows with one such candidate take it; the others are re-ranked with exact float64 products.
The result is the exact arg-min (ties to the lowest id), whatever the centroids; centroids far
from [0, 1] only widen the band and cost time (`flat_quantizer` then keeps the float search).

The int8 product cannot saturate on x86 without VNNI (pairs of products are summed in int16):
one operand is 0 or 1, so a pair sums to at most 2 * 127.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort

from aefabmap.errors import InputError
from aefabmap.runtime.core import compiled
from aefabmap.runtime.core.onnx_matmul import INPUT_NAME, OUTPUT_NAME, matmul_integer_model
from aefabmap.runtime.core.onnx_quantizer import session_options
from aefabmap.runtime.core.quantizer import NearestCentroidQuantizer, check_vectors

_LEVELS = 127  # int8 steps on each side of 1/2
_SAFETY = 1.0  # z units (1/254 of a score unit) on top of beta: float64 rounding of beta itself


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


class BitCentroidQuantizer:
    """Nearest mean centroid of bit vectors (Quantizer protocol), via an int8 product.

    centroids: (K, D) float32, D a multiple of 8 (the unpacked bits of D / 8 bytes).
    threads: onnxruntime intra-op threads. chunk: descriptors per int8 product (bounds the
    (chunk, K) int32 block).
    """

    accepts_packed_bits = True

    def __init__(self, centroids: np.ndarray, threads: int = 1, chunk: int = 512) -> None:
        c = np.asarray(centroids, dtype=np.float32)
        if c.ndim != 2 or c.shape[0] < 1 or c.shape[1] < 8 or c.shape[1] % 8:
            raise InputError(f"bit centroids must be a non-empty (K, D) array with D a multiple of 8, got {c.shape}")
        if not np.isfinite(c).all():
            raise InputError("bit centroids hold NaN or infinite values")
        opts = session_options(threads)
        self.centroids = np.ascontiguousarray(c)
        self._float = NearestCentroidQuantizer(self.centroids)
        self.vocabulary_size, self.descriptor_length = (int(n) for n in c.shape)
        self._chunk = int(chunk)
        c64 = c.astype(np.float64)
        q = np.clip(np.rint(_LEVELS * (2.0 * c64 - 1.0)), -_LEVELS, _LEVELS)
        residual = c64 - (q / _LEVELS + 1.0) / 2.0
        sq_norms = np.einsum("kd,kd->k", c64, c64)
        self._norm_term = np.rint(_LEVELS * sq_norms).astype(np.int32)
        self._half_sq_norms = 0.5 * sq_norms
        #: Half-width of the candidate band, in z units (module doc).
        self.beta = float(0.5 + 2 * _LEVELS * np.abs(residual).sum(axis=1).max() + _SAFETY)
        self._band = np.int32(np.ceil(2.0 * self.beta))
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
            select_kernel()(products, self._norm_term, self._band, bits, self.centroids, self._half_sq_norms, best)
            return best
        return self._select(products, bits)

    def _select(self, z: np.ndarray, bits: np.ndarray) -> np.ndarray:
        """numpy path of `select_kernel`: z (n, K) int32 products, overwritten."""
        z -= self._norm_term
        every = np.arange(z.shape[0])
        best = np.argmax(z, axis=1)
        top = z[every, best]
        # A row needs the re-rank only when its second best is in the band (two cheap passes
        # instead of comparing every product with the band).
        z[every, best] = np.iinfo(np.int32).min
        floor = top - self._band
        ambiguous = np.flatnonzero(z.max(axis=1) >= floor)
        z[every, best] = top
        if ambiguous.size:
            rows, words = np.nonzero(z[ambiguous] >= floor[ambiguous, None])
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


@compiled.kernel
def select_kernel():
    """Per row of int8 products (overwritten with z): the band of candidates, and the exact
    re-rank when it holds more than one (module doc); compiled (runtime/core/compiled.py)."""
    def select(products, norm_term, band, bits, centroids, half_sq_norms, best):
        n, k = products.shape
        d = bits.shape[1]
        for i in range(n):
            z = products[i]
            top = np.int32(-(2**31 - 1))
            for j in range(k):  # z in place and its maximum: branch-free, vectorised
                z[j] -= norm_term[j]
                top = max(top, z[j])
            floor = top - band
            # Words in the band and the sum of their ids, branch-free: with one word in the band
            # (two rows in three), that sum is the word.
            count, where = 0, 0
            for j in range(k):
                inside = z[j] >= floor
                count += inside
                where += j * inside
            if count == 1:
                best[i] = where
                continue
            top_exact, arg = -np.inf, 0
            x = bits[i]
            for j in range(k):
                if z[j] >= floor:
                    c = centroids[j]
                    s = 0.0  # float64 sum of float32 centroid values, in bit order
                    for t in range(d):  # branch-free: a clear bit adds an exact 0.0
                        s += np.float64(c[t]) * x[t]
                    s -= half_sq_norms[j]
                    if s > top_exact:
                        top_exact, arg = s, j
            best[i] = arg

    return compiled.numba.njit(
        "void(int32[:, ::1], int32[::1], int32, uint8[:, ::1], float32[:, ::1], float64[::1], int32[::1])",
        nogil=True, cache=False, boundscheck=False)(select)
