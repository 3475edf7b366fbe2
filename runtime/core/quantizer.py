"""The quantiser interface: descriptor vectors in, visual word ids out.

Implemented by the k-means vocabulary (nearest centroid, here), the vocabulary tree
(runtime/core/vocab_tree.py) and the autoencoder quantiser (one ONNX graph,
runtime/core/onnx_quantizer.py). Callers holding raw descriptors use `quantize_raw`, which
hands packed bits straight to a quantiser that reads them (a tree with binary centres).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from aefabmap.errors import InputError
from aefabmap.runtime.core.feature_kinds import FeatureKind


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
