"""Vocabulary tree (DBoW2-style hierarchical k-means): a word in O(B log_B K) distances, not O(K).

The tree is k-ary (at most B children a node); its leaves are the visual words. A descriptor
goes down from the root, at each node to the nearest child, and takes the leaf's word. Nodes
are numbered breadth-first from the root (node 0, whose centre is unused), so every child id
is larger than its parent's: the tree is acyclic by construction and checkable in O(M).

Binary kinds (ORB) keep packed bit centres (M, W) uint8 and compare with the Hamming distance
by popcount on the packed bytes (8 bytes at a time when W is a multiple of 8); float kinds
(SIFT) keep (M, D) float32 centres and compare with squared L2.
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.kernels.bits import popcount_rows
from aefabmap_runtime.core.words.quantizer import check_vectors

class VocabularyTree:
    """Tree quantiser over the Quantizer protocol (runtime/aefabmap_runtime/core/words/quantizer.py).

    centers: (M, W) uint8 packed bits (binary kinds, Hamming) or (M, D) float32 (squared L2).
    children: (M, B) int32 child node ids, -1 padding after the real ones; a row of -1 is a leaf.
    leaf_words: (M,) int32 word id of each leaf, -1 for inner nodes; the leaves' ids are
        0..V-1, each once. descriptor_length: D of the descriptor vectors (binary: 8 W).
    The arrays are trusted here: the bundle reader validates them (validate_tree) first.
    """

    def __init__(self, centers: np.ndarray, children: np.ndarray, leaf_words: np.ndarray) -> None:
        validate_tree(centers, children, leaf_words)
        self.binary = centers.dtype == np.uint8
        self.centers = np.ascontiguousarray(centers)
        self.children = np.ascontiguousarray(children, np.int32)
        self.leaf_words = np.ascontiguousarray(leaf_words, np.int32)
        self.branching = int(children.shape[1])
        self.vocabulary_size = int((leaf_words >= 0).sum())
        self.descriptor_length = int(centers.shape[1]) * (8 if self.binary else 1)
        self.depth = tree_depth(self.children)
        # Padding children point at a sentinel row whose distance never wins.
        m = centers.shape[0]
        self._kids = np.where(self.children >= 0, self.children, m).astype(np.intp)
        if self.binary:
            self._centers = np.vstack([self.centers, np.zeros((1, centers.shape[1]), np.uint8)])
        else:
            c = self.centers.astype(np.float32)
            self._centers = np.vstack([c, np.zeros((1, c.shape[1]), np.float32)])
            half = 0.5 * np.einsum("md,md->m", c, c)
            self._half_sq = np.concatenate([half, [np.inf]]).astype(np.float32)
        self._is_leaf = np.concatenate([self.children[:, 0] < 0, [True]])

    @property
    def accepts_packed_bits(self) -> bool:
        """True with binary centres: quantize_raw takes packed descriptor bytes (quantizer.quantize_raw)."""
        return self.binary

    @property
    def nodes(self) -> int:
        return int(self.centers.shape[0])

    def quantize(self, vectors: np.ndarray) -> np.ndarray:
        """Descriptor vectors (N, D) float32 -> word ids (N,) int32 (binary: bits >= 0.5 are 1)."""
        x = check_vectors(vectors, self.descriptor_length)
        if self.binary:
            return self._descend_binary(np.packbits(x >= 0.5, axis=1))
        return self._descend_float(x)

    def quantize_raw(self, descriptors: np.ndarray) -> np.ndarray:
        """Raw descriptors -> word ids (N,) int32: binary (N, W) uint8 packed bits, float (N, D)."""
        d = np.asarray(descriptors)
        if self.binary:
            w = self.centers.shape[1]
            if d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != w:
                raise InputError(f"binary descriptors must be (N, {w}) uint8, got {d.shape} {d.dtype}")
            return self._descend_binary(np.ascontiguousarray(d))
        return self._descend_float(check_vectors(d, self.descriptor_length))

    def _descend_binary(self, x: np.ndarray) -> np.ndarray:
        node = np.zeros(x.shape[0], np.intp)
        active = np.arange(x.shape[0])
        padded = self._is_leaf.size - 1
        while active.size:
            kids = self._kids[node[active]]  # (n, B)
            rows = np.take(self._centers, kids, axis=0)  # (n, B, W); take: faster than fancy indexing
            np.bitwise_xor(rows, x[active, None, :], out=rows)
            dist = popcount_rows(rows)
            dist[kids == padded] = np.iinfo(np.int32).max
            # argmin takes the first of equal distances: the same rule as brute force.
            node[active] = kids[np.arange(kids.shape[0]), np.argmin(dist, axis=1)]
            active = active[~self._is_leaf[node[active]]]
        return self.leaf_words[node]

    def _descend_float(self, x: np.ndarray) -> np.ndarray:
        node = np.zeros(x.shape[0], np.intp)
        active = np.arange(x.shape[0])
        while active.size:
            kids = self._kids[node[active]]
            # argmin |x - c|^2 = argmax (x.c - |c|^2 / 2); the sentinel's -inf never wins.
            rows = np.take(self._centers, kids, axis=0)  # (n, B, D)
            score = np.einsum("nbd,nd->nb", rows, x[active]) - self._half_sq[kids]
            node[active] = kids[np.arange(kids.shape[0]), np.argmax(score, axis=1)]
            active = active[~self._is_leaf[node[active]]]
        return self.leaf_words[node]


def tree_depth(children: np.ndarray) -> int:
    """Levels below the root of a breadth-first tree (children ids > parent ids)."""
    level = np.zeros(children.shape[0], np.int64)
    for parent in range(children.shape[0]):
        kids = children[parent][children[parent] >= 0]
        level[kids] = level[parent] + 1
    return int(level.max()) if level.size else 0


def validate_tree(centers: np.ndarray, children: np.ndarray, leaf_words: np.ndarray) -> None:
    """Raise InputError unless the arrays form one vocabulary tree (see VocabularyTree).

    Checked: shapes and dtypes agree; children ids in (parent, M) with -1 only as trailing
    padding; every node but the root has exactly one parent; an inner node has >= 2 children;
    leaves are exactly the nodes without children and carry the word ids 0..V-1 once each;
    float centres are finite.
    """
    if not isinstance(centers, np.ndarray) or centers.ndim != 2 or centers.shape[0] < 3 or centers.shape[1] < 1:
        raise InputError(f"tree centres must be a (M >= 3, W) array, got {getattr(centers, 'shape', None)}")
    if centers.dtype != np.uint8 and centers.dtype != np.float32:
        raise InputError(f"tree centres must be uint8 (packed bits) or float32, got {centers.dtype}")
    m = centers.shape[0]
    if not isinstance(children, np.ndarray) or children.ndim != 2 or children.shape[0] != m or children.shape[1] < 2:
        raise InputError(f"tree children must be ({m}, B >= 2), got {getattr(children, 'shape', None)}")
    if not isinstance(leaf_words, np.ndarray) or leaf_words.shape != (m,):
        raise InputError(f"tree leaf words must be ({m},), got {getattr(leaf_words, 'shape', None)}")
    if children.dtype.kind not in "iu" or leaf_words.dtype.kind not in "iu":
        raise InputError("tree children and leaf words must be integers")
    if centers.dtype == np.float32 and not np.isfinite(centers).all():
        raise InputError("tree centres hold NaN or infinite values")
    ch = children.astype(np.int64)
    valid = ch >= 0
    if np.any(ch < -1) or np.any(ch >= m):
        raise InputError(f"tree children must be node ids in [0, {m}) or -1")
    # -1 only after the real children: once invalid, stays invalid along the row.
    if np.any(valid[:, 1:] & ~valid[:, :-1]):
        raise InputError("tree children: -1 padding must come after a node's children")
    parents = np.broadcast_to(np.arange(m)[:, None], ch.shape)
    if np.any(ch[valid] <= parents[valid]):
        raise InputError("tree children must be numbered after their parent (breadth-first order)")
    n_parents = np.bincount(ch[valid], minlength=m)
    if n_parents[0] != 0 or np.any(n_parents[1:] != 1):
        raise InputError("every tree node but the root must have exactly one parent")
    n_kids = valid.sum(axis=1)
    if n_kids[0] < 2 or np.any(n_kids == 1):
        raise InputError("inner tree nodes must have at least 2 children")
    leaf = n_kids == 0
    words = leaf_words.astype(np.int64)
    if np.any(words[~leaf] != -1):
        raise InputError("inner tree nodes must have leaf word -1")
    v = int(leaf.sum())
    if not np.array_equal(np.sort(words[leaf]), np.arange(v)):
        raise InputError(f"tree leaves must carry the word ids 0..{v - 1}, each once")
