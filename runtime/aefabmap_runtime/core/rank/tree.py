"""The Chow-Liu tree over visual words: the four numbers per word FAB-MAP needs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import InputError


@dataclass(frozen=True)
class ChowLiuTree:
    """A Chow-Liu tree over V words (all arrays have length V).

    parent: int parent word index; the root is its own parent.
    p: P(z_q = 1), the (smoothed) marginal of each word.
    p_given_parent: P(z_q = 1 | z_parent = 1)  ("a"; equals p at the root).
    p_given_not_parent: P(z_q = 1 | z_parent = 0)  ("b"; equals p at the root).
    """

    parent: np.ndarray
    p: np.ndarray
    p_given_parent: np.ndarray
    p_given_not_parent: np.ndarray

    def __post_init__(self) -> None:
        parent = np.asarray(self.parent, dtype=np.int64)
        arrays = {
            "p": np.asarray(self.p, dtype=np.float64),
            "p_given_parent": np.asarray(self.p_given_parent, dtype=np.float64),
            "p_given_not_parent": np.asarray(self.p_given_not_parent, dtype=np.float64),
        }
        if parent.ndim != 1 or parent.size == 0:
            raise InputError(f"tree parent must be a non-empty 1-D array, got shape {parent.shape}")
        v = parent.size
        for name, arr in arrays.items():
            if arr.shape != (v,):
                raise InputError(f"tree {name} has shape {arr.shape}, expected ({v},)")
            if not np.all((arr > 0) & (arr < 1)):
                raise InputError(f"tree {name} must lie strictly inside (0, 1)")
        if parent.min() < 0 or parent.max() >= v:
            raise InputError(f"tree parent indices must lie in [0, {v})")
        roots = np.flatnonzero(parent == np.arange(v))
        if roots.size != 1:
            raise InputError(f"tree must have exactly one root (own parent), found {roots.size}")
        _check_acyclic(parent, int(roots[0]))
        object.__setattr__(self, "parent", parent)
        for name, arr in arrays.items():
            object.__setattr__(self, name, arr)

    @property
    def size(self) -> int:
        """Number of words V."""
        return int(self.parent.size)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent == np.arange(self.size))[0])


def _check_acyclic(parent: np.ndarray, root: int) -> None:
    """Every word must reach the root by following parents (no cycles, one component)."""
    v = parent.size
    reached = np.zeros(v, bool)
    reached[root] = True
    # Pointer doubling: after ceil(log2 V) rounds every node's ancestor at distance
    # 2^k is known; a node reaches the root iff its far ancestor is the root.
    anc = parent.copy()
    for _ in range(max(1, int(np.ceil(np.log2(v))) + 1)):
        anc = anc[anc]
    if not np.all(anc == root):
        raise InputError("tree parent array has a cycle or more than one component")
