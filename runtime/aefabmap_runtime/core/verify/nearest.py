"""Two nearest neighbours of descriptor rows among another set (pure): the all-pairs search of
verification's brute-force retry.

Binary kinds: Hamming distance (`bits.nearest_two`: a compiled popcount kernel, or OpenCV).
Float kinds: L2 distance of unit rows from one matrix product, |q - p| = sqrt(2 - 2 q.p): BLAS
does the 1000 x 1000 x 128 SIFT product several times faster than OpenCV's batchDistance finds
the same neighbours (distances agree to float rounding; docs/results.md, "Per frame").
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.kernels.bits import nearest_two as nearest_two_hamming
from aefabmap_runtime.core.features.feature_kinds import DISTANCES

#: Query rows per matrix product: bounds the similarity block to ROWS x M float32 (2 MB at M = 1000).
ROWS = 512


def nearest_two(q_desc: np.ndarray, p_desc: np.ndarray, distance: str) -> tuple[np.ndarray, np.ndarray]:
    """Each row of q_desc (N, B)'s two nearest rows of p_desc (M, B) -> (distance (N, 2) float32,
    index (N, 2) int64), nearest first; index -1 and distance inf where p_desc has fewer than
    two rows.

    distance "hamming": packed bits (uint8), a tie going to the lower index; "l2": rows are
    scaled to unit length first (float descriptors or their uint8 store form).
    """
    if distance not in DISTANCES:
        raise ConfigError(f"descriptor distance must be one of {DISTANCES}, got {distance!r}")
    if q_desc.ndim != 2 or p_desc.ndim != 2 or q_desc.shape[1] != p_desc.shape[1]:
        raise InputError(f"nearest_two needs rows of one width, got {q_desc.shape} and {p_desc.shape}")
    if distance == "hamming":
        d, i = nearest_two_hamming(q_desc, p_desc)
        missing = i < 0
        d = d.astype(np.float32)
        d[missing] = np.inf
        return d, i.astype(np.int64)
    q, p = unit_rows(q_desc), unit_rows(p_desc)
    n, m = q.shape[0], p.shape[0]
    dist = np.full((n, 2), np.inf, np.float32)
    index = np.full((n, 2), -1, np.int64)
    if n == 0 or m == 0:
        return dist, index
    k = min(2, m)
    for start in range(0, n, ROWS):
        sim = q[start: start + ROWS] @ p.T  # cosine similarity: nearest = largest
        rows = np.arange(sim.shape[0])
        for j in range(k):
            best = sim.argmax(axis=1)
            index[start + rows, j] = best
            dist[start + rows, j] = np.sqrt(np.maximum(2.0 - 2.0 * sim[rows, best], 0.0))
            sim[rows, best] = -np.inf
    return dist, index


def unit_rows(desc: np.ndarray) -> np.ndarray:
    """Descriptors (float or stored uint8) -> float32 rows of unit L2 norm."""
    d = desc.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
