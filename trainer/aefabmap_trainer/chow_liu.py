"""Chow-Liu tree learning from binary image-word observations, sparse and exact.

Follows docs/fabmap2.md: smoothed marginals, raw joint frequencies, mutual
information over the 4 cells, maximum-weight spanning tree, root at the first word of the
highest-MI edge, smoothed conditionals.

Scale: co-occurrence counts come from sparse products X^T X computed one block of words at
a time; each block's edges are reduced to a maximum spanning forest before merging (an edge
left out of a block's forest closes a cycle of heavier edges, so it cannot be in the tree).
Memory is bounded by the block size, not by V^2.

Word pairs that never co-occur have no entry in X^T X, yet their MI is not zero. They are
included exactly for the `dense_words` most frequent words (all pairs when V <= dense_words);
other components left over are joined through their most frequent word (see `_join_components`).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.rank.tree import ChowLiuTree

# Any MI is < 10 nats here (a cell's log ratio is at most log(1 / 0.01^2) = 9.2), so
# OFFSET - MI is a positive edge weight and a minimum spanning tree of it is a maximum one of MI.
_OFFSET = 20.0


def observations_matrix(observations, vocabulary_size: int | None = None) -> sparse.csr_matrix:
    """Binary N x V CSR matrix (float32 ones) from a dense/sparse matrix or a list of word-id arrays."""
    if sparse.issparse(observations):
        x = sparse.csr_matrix(observations, dtype=np.float32)
        x.data[:] = 1.0
        x.eliminate_zeros()
        x.sum_duplicates()
        x.data[:] = 1.0
        return x
    if isinstance(observations, np.ndarray) and observations.ndim == 2:
        return sparse.csr_matrix((observations != 0).astype(np.float32))
    rows = [np.unique(np.asarray(o, dtype=np.int64)) for o in observations]
    if vocabulary_size is None:
        vocabulary_size = 1 + max((int(r[-1]) for r in rows if r.size), default=0)
    indptr = np.concatenate([[0], np.cumsum([r.size for r in rows])]).astype(np.int64)
    indices = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= vocabulary_size):
        raise InputError(f"word ids must lie in [0, {vocabulary_size})")
    data = np.ones(indices.size, np.float32)
    return sparse.csr_matrix((data, indices, indptr), shape=(len(rows), vocabulary_size))


def mutual_information(n11, c_i, c_j, n: int) -> np.ndarray:
    """MI of word pairs from counts: n11 co-occurrences, c_i / c_j word counts, n images.

    Joint cells are raw frequencies; marginals are smoothed 0.98 c / n + 0.01; cells with
    zero frequency contribute nothing.
    """
    n11 = np.asarray(n11, np.float64)
    c_i = np.asarray(c_i, np.float64)
    c_j = np.asarray(c_j, np.float64)
    pi = 0.98 * c_i / n + 0.01
    pj = 0.98 * c_j / n + 0.01
    mi = np.zeros(np.broadcast(n11, c_i, c_j).shape)
    cells = (
        (n11, pi, pj),
        (c_i - n11, pi, 1.0 - pj),
        (c_j - n11, 1.0 - pi, pj),
        (n - c_i - c_j + n11, 1.0 - pi, 1.0 - pj),
    )
    for count, a, b in cells:
        joint = count / n
        pos = joint > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            term = joint * np.log(joint / (a * b))
        mi += np.where(pos, term, 0.0)
    return mi


def fit_chow_liu(
    observations,
    vocabulary_size: int | None = None,
    *,
    dense_words: int = 2000,
    block_nnz: int = 4_000_000,
) -> ChowLiuTree:
    """Learn a ChowLiuTree from N binary observations.

    observations: N x V binary matrix (numpy or scipy-sparse) or a list of word-id arrays.
    dense_words: MI of never-co-occurring pairs is included exactly among this many most
        frequent words. block_nnz: bound on co-occurrence entries held at once.
    """
    x = observations_matrix(observations, vocabulary_size)
    n, v = x.shape
    if n == 0:
        raise InputError("Chow-Liu learning needs at least one training observation")
    if v < 2:
        raise InputError("Chow-Liu learning needs at least two words")
    counts = np.asarray(x.sum(axis=0)).ravel().astype(np.int64)
    xc = x.tocsc()
    forest = _empty_edges()
    for lo, hi in _word_blocks(xc, block_nnz):
        forest = _spanning_forest(_merge(forest, _cooccurring_edges(xc, x, counts, n, lo, hi)), v)
    forest = _spanning_forest(_merge(forest, _frequent_zero_pair_edges(xc, counts, n, dense_words)), v)
    forest = _join_components(forest, counts, v)
    return _tree_from_edges(forest, x, counts, n, v)


def _empty_edges():
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64)


def _merge(a, b):
    return tuple(np.concatenate([p, q]) for p, q in zip(a, b))


def _word_blocks(xc: sparse.csc_matrix, block_nnz: int):
    """Yield word ranges [lo, hi) whose co-occurrence rows hold about block_nnz entries."""
    v = xc.shape[1]
    # Row q of X^T X has at most min(V, sum of the sizes of q's images) entries.
    image_sizes = np.diff(xc.tocsr().indptr).astype(np.float64)
    per_word = np.minimum(xc.T @ image_sizes, v).astype(np.int64)
    lo = 0
    while lo < v:
        acc = np.cumsum(per_word[lo:])
        hi = lo + max(1, int(np.searchsorted(acc, block_nnz, side="right")))
        yield lo, min(hi, v)
        lo = hi


def _cooccurring_edges(xc, x, counts, n, lo, hi):
    """Edges (i, j, MI) with i in [lo, hi), j > i, for pairs that co-occur at least once."""
    block = (xc[:, lo:hi].T @ x).tocoo()
    rows = block.row.astype(np.int64) + lo
    cols = block.col.astype(np.int64)
    upper = cols > rows
    rows, cols, n11 = rows[upper], cols[upper], block.data[upper].astype(np.float64)
    return rows, cols, mutual_information(n11, counts[rows], counts[cols], n)


def _frequent_zero_pair_edges(xc, counts, n, dense_words):
    """Edges between the most frequent words that never co-occur (absent from X^T X)."""
    v = counts.size
    top = np.sort(np.argsort(-counts, kind="stable")[: min(dense_words, v)])
    sub = xc[:, top]
    co = (sub.T @ sub).toarray()
    i, j = np.nonzero(np.triu(co == 0, k=1))
    wi, wj = top[i], top[j]
    return wi, wj, mutual_information(np.zeros(wi.size), counts[wi], counts[wj], n)


def _spanning_forest(edges, v):
    """Maximum-MI spanning forest of the given edges (Kruskal-equivalent, via scipy)."""
    i, j, mi = edges
    if i.size == 0:
        return edges
    g = sparse.coo_matrix((_OFFSET - mi, (i, j)), shape=(v, v)).tocsr()
    t = csgraph.minimum_spanning_tree(g).tocoo()
    ti, tj = np.minimum(t.row, t.col).astype(np.int64), np.maximum(t.row, t.col).astype(np.int64)
    return ti, tj, _OFFSET - t.data


def _join_components(forest, counts, v):
    """Join the forest's components into one tree.

    Each component is attached through its most frequent word to the most frequent word
    of the largest component (for pairs that never co-occur, MI grows with both words'
    frequencies, so this is the heaviest such edge available). The edge gets weight -inf so
    that it never becomes the root edge.
    """
    i, j, mi = forest
    g = sparse.coo_matrix((np.ones(i.size), (i, j)), shape=(v, v))
    n_comp, labels = csgraph.connected_components(g, directed=False)
    if n_comp == 1:
        return forest
    sizes = np.bincount(labels)
    main = int(np.argmax(sizes))
    order = np.argsort(-counts, kind="stable")
    first = {}
    for w in order.tolist():
        first.setdefault(int(labels[w]), w)
        if len(first) == n_comp:
            break
    hub = first[main]
    extra_i, extra_j = [], []
    for comp, w in sorted(first.items()):
        if comp != main:
            extra_i.append(min(hub, w))
            extra_j.append(max(hub, w))
    k = len(extra_i)
    return (
        np.concatenate([i, np.array(extra_i, np.int64)]),
        np.concatenate([j, np.array(extra_j, np.int64)]),
        np.concatenate([mi, np.full(k, -np.inf)]),
    )


def _tree_from_edges(forest, x, counts, n, v) -> ChowLiuTree:
    i, j, mi = forest
    best = int(np.argmax(mi))
    # Ties between equal-MI edges go to the lowest (i, j), as a sorted Kruskal would see them.
    cand = np.flatnonzero(mi == mi[best])
    best = int(cand[np.lexsort((j[cand], i[cand]))[0]])
    root = int(i[best])
    g = sparse.coo_matrix((np.ones(i.size), (i, j)), shape=(v, v)).tocsr()
    _, pred = csgraph.breadth_first_order(g, root, directed=False, return_predecessors=True)
    parent = pred.astype(np.int64)
    parent[root] = root
    if np.any(parent < 0):
        raise InputError("internal error: the spanning tree does not reach every word")
    p = 0.98 * counts / n + 0.01
    q = np.arange(v)
    kids = q != root
    xc = x.tocsc()
    # n(q and parent) for every word: one sparse element-wise product per word pair.
    both = np.asarray(xc[:, q[kids]].multiply(xc[:, parent[kids]]).sum(axis=0)).ravel()
    c_par = counts[parent[kids]].astype(np.float64)
    c_notpar = n - c_par
    n_q_notpar = counts[kids] - both
    a = np.full(v, 0.01)
    b = np.full(v, 0.01)
    with np.errstate(divide="ignore", invalid="ignore"):
        a[kids] = np.where(c_par > 0, 0.98 * both / c_par + 0.01, 0.01)
        b[kids] = np.where(c_notpar > 0, 0.98 * n_q_notpar / c_notpar + 0.01, 0.01)
    a[root] = b[root] = p[root]
    return ChowLiuTree(parent, p, a, b)
