"""The quantiser interface: descriptor vectors in, visual word ids out.

Implemented by the k-means vocabulary (nearest centroid, here), the vocabulary tree
(runtime/aefabmap_runtime/core/words/vocab_tree.py) and the autoencoder quantiser (one ONNX graph,
runtime/aefabmap_runtime/core/words/onnx_quantizer.py). Callers holding raw descriptors use `quantize_raw`, which
hands packed bits straight to a quantiser that reads them (a tree with binary centres).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.features.feature_kinds import FeatureKind


@runtime_checkable
class Quantizer(Protocol):
    """Maps descriptor vectors (N, D) float32 to word ids (N,) int32 in [0, vocabulary_size)."""

    vocabulary_size: int
    descriptor_length: int

    def quantize(self, vectors: np.ndarray) -> np.ndarray: ...


def quantize_raw(quantizer: Quantizer, kind: FeatureKind, descriptors: np.ndarray) -> np.ndarray:
    """Raw descriptors (N, width) of `kind` -> word ids (N,) int32.

    A quantiser with `accepts_packed_bits` true takes a binary kind's packed bytes as they are
    (no unpacking to 8 W floats); every other gets the kind's descriptor vectors.
    """
    if kind.distance == "hamming" and getattr(quantizer, "accepts_packed_bits", False):
        return quantizer.quantize_raw(kind.check(descriptors))
    return quantizer.quantize(kind.vectors(descriptors))


def check_vectors(vectors: np.ndarray, descriptor_length: int) -> np.ndarray:
    """Validate (N, D) descriptor vectors and return them as C-contiguous float32."""
    vectors = np.asarray(vectors)
    if vectors.ndim != 2 or vectors.shape[1] != descriptor_length:
        raise InputError(f"descriptor vectors must have shape (N, {descriptor_length}), got {vectors.shape}")
    return np.ascontiguousarray(vectors, dtype=np.float32)


class NearestCentroidQuantizer:
    """Flat vocabulary: each vector goes to its nearest centroid (squared L2).

    centroids: (K, D) float32. For ORB bit vectors squared L2 to a 0/1 centroid is the
    Hamming distance, and to a mean centroid its natural real-valued extension.
    """

    def __init__(self, centroids: np.ndarray, chunk: int = 4096) -> None:
        centroids = np.asarray(centroids, dtype=np.float32)
        if centroids.ndim != 2 or centroids.shape[0] < 1:
            raise InputError(f"centroids must be a non-empty (K, D) array, got {centroids.shape}")
        self.centroids = np.ascontiguousarray(centroids)
        self._half_sq_norms = 0.5 * np.einsum("kd,kd->k", self.centroids, self.centroids)
        self.vocabulary_size = int(centroids.shape[0])
        self.descriptor_length = int(centroids.shape[1])
        self._chunk = chunk

    def quantize(self, vectors: np.ndarray) -> np.ndarray:
        x = check_vectors(vectors, self.descriptor_length)
        out = np.empty(x.shape[0], np.int32)
        # argmin ||x - c||^2 = argmax (x.c - |c|^2/2): one BLAS product per chunk.
        for s in range(0, x.shape[0], self._chunk):
            scores = x[s : s + self._chunk] @ self.centroids.T
            scores -= self._half_sq_norms
            out[s : s + self._chunk] = np.argmax(scores, axis=1)
        return out


class IndexedCentroidQuantizer:
    """Flat vocabulary searched through an inverted index: the same words, fewer distances.

    centroids: (K, D) float32, the flat vocabulary. route_centers: (S, W) uint8 packed bits
    (binary kinds: routed by popcount Hamming) or (S, D) float32 (squared L2). indptr (S+1,)
    int64 / words (nnz,) int32: CSR lists, bucket s holds words[indptr[s]:indptr[s+1]].
    A vector goes to its nearest routing centre, then to the nearest centroid (squared L2, as
    NearestCentroidQuantizer) among that bucket's words. The trainer fills each bucket with the
    exact nearest word of every training vector routed to it, so on the training vectors the
    result equals the flat arg-min; elsewhere it is the flat word unless that word never won
    a training vector in the bucket (measured: docs/results.md).
    """

    def __init__(self, centroids: np.ndarray, route_centers: np.ndarray, indptr: np.ndarray, words: np.ndarray) -> None:
        self.flat = NearestCentroidQuantizer(centroids)
        self.vocabulary_size, self.descriptor_length = self.flat.vocabulary_size, self.flat.descriptor_length
        validate_index(route_centers, indptr, words, self.vocabulary_size, self.descriptor_length)
        self.binary = route_centers.dtype == np.uint8
        self.route_centers = np.ascontiguousarray(route_centers)
        self.indptr = np.asarray(indptr, np.int64)
        self.words = np.asarray(words, np.int32)
        self.buckets = int(route_centers.shape[0])
        c = self.flat.centroids
        # Each bucket's centroids contiguous (nnz x D floats): one small product per bucket hit.
        self._bucket_centroids = [np.ascontiguousarray(c[self.words[a:b]]) for a, b in zip(self.indptr[:-1], self.indptr[1:])]
        self._bucket_half = [0.5 * np.einsum("kd,kd->k", m, m) for m in self._bucket_centroids]
        if not self.binary:
            self._route_half = 0.5 * np.einsum("sd,sd->s", route_centers, route_centers)

    @property
    def accepts_packed_bits(self) -> bool:
        return self.binary

    def quantize(self, vectors: np.ndarray) -> np.ndarray:
        """Descriptor vectors (N, D) float32 -> word ids (N,) int32."""
        x = check_vectors(vectors, self.descriptor_length)
        if self.binary:
            return self._search(x, self._route_packed(np.packbits(x >= 0.5, axis=1)))
        scores = x @ self.route_centers.T - self._route_half
        return self._search(x, np.argmax(scores, axis=1))

    def quantize_raw(self, descriptors: np.ndarray) -> np.ndarray:
        """Packed binary descriptors (N, W) uint8 -> word ids (N,) int32 (binary index only)."""
        d = np.asarray(descriptors)
        w = self.descriptor_length // 8
        if not self.binary or d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != w:
            raise InputError(f"quantize_raw needs (N, {w}) uint8 packed bits and a binary index, got {d.shape} {d.dtype}")
        d = np.ascontiguousarray(d)
        return self._search(np.unpackbits(d, axis=1).astype(np.float32), self._route_packed(d))

    def _route_packed(self, packed: np.ndarray) -> np.ndarray:
        return route_packed(self.route_centers, packed)

    def _search(self, x: np.ndarray, bucket: np.ndarray) -> np.ndarray:
        out = np.empty(x.shape[0], np.int32)
        order = np.argsort(bucket, kind="stable")
        sorted_b = bucket[order]
        starts = np.flatnonzero(np.r_[True, sorted_b[1:] != sorted_b[:-1]]) if order.size else np.zeros(0, np.intp)
        ends = np.r_[starts[1:], order.size]
        for s, e in zip(starts, ends):
            b = int(sorted_b[s])
            rows = order[s:e]
            scores = x[rows] @ self._bucket_centroids[b].T
            scores -= self._bucket_half[b]
            out[rows] = self.words[self.indptr[b] + np.argmax(scores, axis=1)]
        return out


def route_packed(route_centers: np.ndarray, packed: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Nearest packed-bit routing centre (S, W) uint8 of each packed row (N, W) uint8 -> (N,) int
    (popcount Hamming; first of equal distances)."""
    from aefabmap_runtime.core.kernels.bits import popcount_rows

    out = np.empty(packed.shape[0], np.intp)
    for s in range(0, packed.shape[0], chunk):
        x = np.bitwise_xor(route_centers[None, :, :], packed[s : s + chunk, None, :])  # (n, S, W)
        out[s : s + chunk] = np.argmin(popcount_rows(x), axis=1)
    return out


def validate_index(route_centers: np.ndarray, indptr: np.ndarray, words: np.ndarray, k: int, d: int) -> None:
    """Raise InputError unless the arrays are an index over k words of d-dim vectors.

    Checked: routing centres (S, d/8) uint8 or (S, d) float32 (finite), S >= 1; indptr (S+1,)
    from 0, non-decreasing, ending at len(words); every bucket non-empty; word ids in [0, k),
    unique within a bucket; every word in some bucket.
    """
    if not isinstance(route_centers, np.ndarray) or route_centers.ndim != 2 or route_centers.shape[0] < 1:
        raise InputError(f"index routing centres must be a non-empty (S, W) array, got {getattr(route_centers, 'shape', None)}")
    if route_centers.dtype == np.uint8:
        if d % 8 or route_centers.shape[1] != d // 8:
            raise InputError(f"packed routing centres must be (S, {d // 8}) for {d}-bit vectors")
    elif route_centers.dtype == np.float32:
        if route_centers.shape[1] != d or not np.isfinite(route_centers).all():
            raise InputError(f"float routing centres must be finite (S, {d})")
    else:
        raise InputError(f"index routing centres must be uint8 or float32, got {route_centers.dtype}")
    s = route_centers.shape[0]
    if not isinstance(indptr, np.ndarray) or indptr.shape != (s + 1,) or indptr.dtype.kind not in "iu":
        raise InputError(f"index indptr must be ({s + 1},) integers")
    if not isinstance(words, np.ndarray) or words.ndim != 1 or words.dtype.kind not in "iu":
        raise InputError("index words must be a 1-D integer array")
    p = indptr.astype(np.int64)
    if p[0] != 0 or p[-1] != words.size or np.any(np.diff(p) < 1):
        raise InputError("index indptr must start at 0, grow by >= 1 per bucket and end at len(words)")
    w = words.astype(np.int64)
    if w.size and (w.min() < 0 or w.max() >= k):
        raise InputError(f"index words must be word ids in [0, {k})")
    bucket_of = np.repeat(np.arange(s), np.diff(p))
    if np.unique(bucket_of * k + w).size != w.size:
        raise InputError("index words repeat within a bucket")
    if np.unique(w).size != k:
        raise InputError("every word must be in some index bucket")
