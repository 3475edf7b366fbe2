"""Train a vocabulary tree (runtime/aefabmap_runtime/core/words/vocab_tree.py): k-means per node, exactly K leaves.

DBoW2's recipe (k-means++ seeded Lloyd's at every node, k-majority centres for binary
descriptors, leaves are the words) with one change: instead of a fixed depth L giving up to
B^L leaves, each node gets a leaf budget (the root: K) that it shares among its children in
proportion to the training vectors they receive, so the tree has exactly K words and can be
compared with a flat vocabulary of the same size. A node with a budget of at most B splits
into that many leaves.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_trainer.kmeans import KMeansConfig, assign, fit_kmeans

#: Bounds of the branching factor (children per node).
MIN_BRANCHING, MAX_BRANCHING = 2, 256


@dataclass(frozen=True)
class VocabTreeArrays:
    """The arrays of a trained tree (see VocabularyTree) and what training saw.

    centers: (M, W) uint8 packed bits when binary, else (M, D) float32. children: (M, B) int32.
    leaf_words: (M,) int32. leaf_counts: (V,) training vectors per word.
    """

    centers: np.ndarray
    children: np.ndarray
    leaf_words: np.ndarray
    leaf_counts: np.ndarray

    @property
    def words(self) -> int:
        return int(self.leaf_counts.size)


def fit_vocab_tree(
    vectors: np.ndarray, words: int, branching: int, *, binary: bool, config: KMeansConfig | None = None, progress=None
) -> VocabTreeArrays:
    """Hierarchical k-means of (N, D) descriptor vectors into a tree with `words` leaves.

    binary: vectors are bits in {0, 1}; centres are k-majority (0/1) and stored packed.
    Deterministic for a given config.seed (each node's k-means is seeded by seed and node id).
    Fewer than `words` leaves only when the vectors have too few distinct rows somewhere.
    progress: optional callable(nodes_done) after each split.
    """
    config = config or KMeansConfig()
    x = np.ascontiguousarray(vectors, dtype=np.float32)
    if x.ndim != 2:
        raise InputError(f"a vocabulary tree needs (N, D) vectors, got shape {x.shape}")
    if not MIN_BRANCHING <= branching <= MAX_BRANCHING:
        raise ConfigError(f"branching must be in [{MIN_BRANCHING}, {MAX_BRANCHING}], got {branching}")
    if words < 2:
        raise ConfigError(f"vocabulary size must be >= 2, got {words}")
    if x.shape[0] < words:
        raise InputError(f"a vocabulary tree of {words} words needs at least {words} vectors, got {x.shape[0]}")
    if binary and not np.isin(x, (0.0, 1.0)).all():
        raise InputError("binary=True needs bit vectors in {0, 1}")

    centers = [np.zeros(x.shape[1], np.float32)]  # the root's centre is never compared
    children: list[list[int]] = [[]]
    members: list[np.ndarray | None] = [None]  # training vectors of each leaf, for the counts
    queue = deque([(0, np.arange(x.shape[0]), words)])
    while queue:
        node, idx, budget = queue.popleft()
        split = _split(x[idx], min(branching, budget), binary, config, node) if budget >= 2 else None
        if split is None:
            members[node] = idx
            continue
        child_centers, labels = split
        counts = np.bincount(labels, minlength=len(child_centers))
        shares = _share_budget(budget, counts)
        for c, center in enumerate(child_centers):
            child = len(centers)
            centers.append(center)
            children.append([])
            members.append(None)
            children[node].append(child)
            queue.append((child, idx[labels == c], int(shares[c])))
        if progress is not None:
            progress(node)

    m = len(centers)
    child_table = np.full((m, branching), -1, np.int32)
    for node, kids in enumerate(children):
        child_table[node, : len(kids)] = kids
    leaf = child_table[:, 0] < 0
    leaf_words = np.full(m, -1, np.int32)
    leaf_words[leaf] = np.arange(int(leaf.sum()), dtype=np.int32)
    leaf_counts = np.array([members[n].size for n in np.flatnonzero(leaf)], np.int64)
    c = np.stack(centers).astype(np.float32)
    out_centers = np.packbits(c >= 0.5, axis=1) if binary else c
    return VocabTreeArrays(out_centers, child_table, leaf_words, leaf_counts)


def _split(x: np.ndarray, k: int, binary: bool, config: KMeansConfig, node: int):
    """k-means of one node's vectors into at most k children: (centres (c, D), labels (n,)) or None.

    None (the node stays a leaf) when fewer than 2 distinct vectors or non-empty clusters remain.
    """
    k = min(k, _distinct_rows(x))
    if k < 2:
        return None
    cfg = KMeansConfig(config.max_iterations, config.tolerance, seed=config.seed * 1_000_003 + node, binary=binary)
    centers = fit_kmeans(x, k, cfg)
    # Labels by the runtime's rule (nearest centre, first of equal distances); on 0/1 vectors and
    # centres the float distances are exact integers, so training routes as the runtime will.
    labels = assign(x, centers)
    used = np.flatnonzero(np.bincount(labels, minlength=k))
    if used.size < 2:
        return None
    if used.size < k:  # a centre that won no vector of its node: drop it, relabel
        centers = centers[used]
        labels = assign(x, centers)
    return centers, labels


def _distinct_rows(x: np.ndarray) -> int:
    rows = np.ascontiguousarray(x).view(np.dtype((np.void, x.dtype.itemsize * x.shape[1]))).ravel()
    return int(np.unique(rows).size)


def _share_budget(budget: int, counts: np.ndarray) -> np.ndarray:
    """Leaf budgets of the children: proportional to their vectors (largest remainder), each in
    [1, count], summing to `budget` (or to sum(counts) when that is smaller)."""
    counts = np.asarray(counts, np.int64)
    total = min(budget, int(counts.sum()))
    quota = total * counts / counts.sum()
    share = np.clip(np.floor(quota).astype(np.int64), 1, counts)
    order = np.argsort(-(quota - share), kind="stable")
    while share.sum() < total:
        for i in order:
            if share.sum() >= total:
                break
            if share[i] < counts[i]:
                share[i] += 1
    while share.sum() > total:  # the floor of 1 gave too many: take back from the largest
        share[np.argmax(share)] -= 1
    return share
