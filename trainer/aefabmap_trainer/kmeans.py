"""k-means vocabulary on descriptor vectors (the FABMAP2 baseline).

ORB descriptors are clustered as unpacked bit vectors in {0,1}^256 with squared-L2 Lloyd's:
for bit vectors squared L2 is the Hamming distance, and the real-valued mean centroid is the
minimiser of summed Hamming distance relaxed to [0,1]^256, a finer quantiser than the
majority-vote binarised centroid (k-majority). SIFT vectors are clustered as they are. Both
share one code path and one runtime quantiser (nearest centroid by squared L2), which is also
the input the autoencoder sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError


@dataclass(frozen=True)
class KMeansConfig:
    """Lloyd's k-means: iterations, convergence tolerance (fraction of reassigned vectors), seed.

    binary: k-majority for bit vectors in {0, 1}: each update rounds the centroids to 0/1 (the
    bitwise majority of the cluster), so centroids pack to bits and compare by popcount.
    """

    max_iterations: int = 25
    tolerance: float = 0.001
    seed: int = 0
    binary: bool = False


def fit_kmeans(vectors: np.ndarray, k: int, config: KMeansConfig | None = None, progress=None) -> np.ndarray:
    """Cluster (N, D) float32 vectors into k centroids (k, D) float32, deterministically.

    Initialisation: k-means++ on a subsample of max(4 k, 20000) vectors (seeded); empty
    clusters are re-seeded with the vectors farthest from their centroid. progress: optional callable(iteration, moved).
    """
    config = config or KMeansConfig()
    x = np.ascontiguousarray(vectors, dtype=np.float32)
    if x.ndim != 2:
        raise InputError(f"k-means needs a (N, D) array, got shape {x.shape}")
    if k < 2:
        raise ConfigError(f"vocabulary size must be >= 2, got {k}")
    if x.shape[0] < k:
        raise InputError(f"k-means needs at least k={k} vectors, got {x.shape[0]}")
    rng = np.random.default_rng(config.seed)
    centroids = _kmeans_plus_plus(x, k, rng)
    labels = np.full(x.shape[0], -1, np.int64)
    for it in range(config.max_iterations):
        new_labels, dist = _assign(x, centroids)
        moved = float(np.mean(new_labels != labels))
        labels = new_labels
        centroids = _update(x, labels, dist, centroids)
        if config.binary:
            # Ties (exactly half the cluster) go to 1: a fixed rule keeps the result reproducible.
            centroids = (centroids >= 0.5).astype(np.float32)
        if progress is not None:
            progress(it, moved)
        if moved <= config.tolerance:
            break
    return centroids


def assign(x: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Nearest centroid (squared L2) of each (N, D) vector -> (N,) int64; first of equal distances."""
    return _assign(np.ascontiguousarray(x, np.float32), np.ascontiguousarray(centroids, np.float32))[0]


def _kmeans_plus_plus(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (D^2 sampling) on a random subsample; distinct seeds guaranteed."""
    m = min(x.shape[0], max(4 * k, 20_000))
    sub = x[np.sort(rng.choice(x.shape[0], m, replace=False))] if m < x.shape[0] else x
    sq = np.einsum("nd,nd->n", sub, sub)
    seeds = np.empty((k, x.shape[1]), np.float32)

    def dist2(c: np.ndarray) -> np.ndarray:
        return np.maximum(sq - 2.0 * (sub @ c) + float(c @ c), 0.0)

    seeds[0] = sub[rng.integers(m)]
    d2 = dist2(seeds[0])
    for c in range(1, k):
        total = float(d2.sum())
        if total <= 0:
            raise InputError(f"only {c} distinct vectors for k={k} clusters")
        idx = int(np.searchsorted(np.cumsum(d2), rng.random() * total, side="right"))
        seeds[c] = sub[min(idx, m - 1)]
        np.minimum(d2, dist2(seeds[c]), out=d2)
    return seeds


def _assign(x: np.ndarray, centroids: np.ndarray, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Nearest centroid of each vector and the squared distance to it."""
    half = 0.5 * np.einsum("kd,kd->k", centroids, centroids)
    sq = np.einsum("nd,nd->n", x, x)
    labels = np.empty(x.shape[0], np.int64)
    dist = np.empty(x.shape[0], np.float32)
    for s in range(0, x.shape[0], chunk):
        scores = x[s : s + chunk] @ centroids.T
        scores -= half
        lab = np.argmax(scores, axis=1)
        labels[s : s + chunk] = lab
        dist[s : s + chunk] = np.maximum(sq[s : s + chunk] - 2.0 * scores[np.arange(lab.size), lab], 0.0)
    return labels, dist


def _update(x: np.ndarray, labels: np.ndarray, dist: np.ndarray, old: np.ndarray) -> np.ndarray:
    k, d = old.shape
    sums = np.zeros((k, d), np.float64)
    _add_rows(sums, labels, x)
    counts = np.bincount(labels, minlength=k)
    centroids = old.copy()
    full = counts > 0
    centroids[full] = (sums[full] / counts[full, None]).astype(np.float32)
    empty = np.flatnonzero(~full)
    if empty.size:
        far = np.argsort(-dist, kind="stable")[: empty.size]
        centroids[empty] = x[far]
    return centroids


def _add_rows(sums: np.ndarray, labels: np.ndarray, x: np.ndarray) -> None:
    """sums[labels[i]] += x[i], via a sort and reduceat (np.add.at is slow on big inputs)."""
    order = np.argsort(labels, kind="stable")
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    sums[lab[starts]] += np.add.reduceat(x[order].astype(np.float64), starts, axis=0)
