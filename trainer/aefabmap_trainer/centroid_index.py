"""Build the inverted index of a flat vocabulary (runtime/aefabmap_runtime/core/words/quantizer.py IndexedCentroidQuantizer).

Routing centres: k-means of the training sample into S buckets (k-majority bit centres for
binary kinds, compared by popcount). Bucket lists: the exact nearest word of every training
descriptor routed to the bucket, plus each word in the bucket its own centroid routes to, so
the index gives the flat words on every training descriptor and every word is reachable.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.words.quantizer import route_packed
from aefabmap_trainer.kmeans import KMeansConfig, assign, fit_kmeans


def fit_routing(sample: np.ndarray, buckets: int, *, binary: bool, config: KMeansConfig) -> np.ndarray:
    """Routing centres of (N, D) vectors: (S, D/8) packed uint8 when binary, else (S, D) float32."""
    if not 1 <= buckets <= sample.shape[0]:
        raise ConfigError(f"index buckets must be in [1, {sample.shape[0]}], got {buckets}")
    if buckets == 1:
        c = (sample.mean(axis=0, keepdims=True) >= 0.5).astype(np.float32) if binary else sample.mean(0, keepdims=True)
    else:
        cfg = KMeansConfig(config.max_iterations, config.tolerance, seed=config.seed, binary=binary)
        c = fit_kmeans(sample, buckets, cfg)
    return np.packbits(c >= 0.5, axis=1) if binary else np.ascontiguousarray(c, np.float32)


def route(route_centers: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Bucket of each (N, D) float32 descriptor vector, by the runtime's rule."""
    if route_centers.dtype == np.uint8:
        return route_packed(route_centers, np.packbits(vectors >= 0.5, axis=1))
    return assign(vectors, route_centers)


def build_lists(route_centers: np.ndarray, centroids: np.ndarray, assigned: Iterable[tuple[np.ndarray, np.ndarray]]):
    """CSR bucket lists (indptr (S+1,) int64, words (nnz,) int32).

    assigned: (vectors (n, D) float32, their exact flat words (n,)) pairs, e.g. per training image.
    """
    s, k = route_centers.shape[0], centroids.shape[0]
    member = np.zeros((s, k), bool)
    member[route(route_centers, centroids), np.arange(k)] = True
    for vectors, words in assigned:
        if len(words):
            member[route(route_centers, vectors), words] = True
    indptr = np.concatenate([[0], np.cumsum(member.sum(axis=1))]).astype(np.int64)
    words = np.flatnonzero(member.ravel()) % k  # row-major: bucket by bucket, words ascending
    return indptr, words.astype(np.int32)
