"""Chow-Liu learning: exact against a dense brute force (docs/fabmap2.md), spanning on sparse data."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import sparse

from aefabmap import ChowLiuTree
from aefabmap_trainer.chow_liu import fit_chow_liu, mutual_information


def dense_reference(x: np.ndarray):
    """openFABMAP's recipe on a dense matrix: MI of all pairs, Kruskal descending, BFS from root."""
    n, v = x.shape
    c = x.sum(0)
    p = 0.98 * c / n + 0.01
    edges = []
    for i, j in itertools.combinations(range(v), 2):
        mi = 0.0
        for xi, xj in itertools.product((0, 1), repeat=2):
            joint = np.mean((x[:, i] == xi) & (x[:, j] == xj))
            if joint > 0:
                mi += joint * np.log(joint / ((p[i] if xi else 1 - p[i]) * (p[j] if xj else 1 - p[j])))
        edges.append((mi, i, j))
    edges.sort(key=lambda e: (-e[0], e[1], e[2]))
    comp = list(range(v))

    def find(a):
        while comp[a] != a:
            comp[a] = comp[comp[a]]
            a = comp[a]
        return a

    tree_edges = []
    for mi, i, j in edges:
        ri, rj = find(i), find(j)
        if ri != rj:
            comp[ri] = rj
            tree_edges.append((i, j))
    root = edges[0][1]
    adj = {q: [] for q in range(v)}
    for i, j in tree_edges:
        adj[i].append(j)
        adj[j].append(i)
    parent = np.full(v, -1)
    parent[root] = root
    stack = [root]
    while stack:
        u = stack.pop()
        for w in adj[u]:
            if parent[w] < 0:
                parent[w] = u
                stack.append(w)
    a = np.empty(v)
    b = np.empty(v)
    for q in range(v):
        pq = parent[q]
        on, off = x[:, pq] == 1, x[:, pq] == 0
        a[q] = 0.98 * x[on, q].sum() / on.sum() + 0.01 if on.sum() else 0.01
        b[q] = 0.98 * x[off, q].sum() / off.sum() + 0.01 if off.sum() else 0.01
    a[root] = b[root] = p[root]
    return parent, p, a, b, set(map(frozenset, tree_edges))


def edge_set(tree: ChowLiuTree):
    return {frozenset((q, int(tree.parent[q]))) for q in range(tree.size) if tree.parent[q] != q}


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_matches_dense_reference(seed):
    rng = np.random.default_rng(seed)
    x = (rng.random((150, 15)) < rng.uniform(0.05, 0.5, 15)).astype(np.int8)
    x[:, 4] = x[:, 2] | x[:, 3]  # real dependencies
    x[:, 7] = x[:, 6] & (rng.random(150) < 0.8)
    parent, p, a, b, edges = dense_reference(x)
    tree = fit_chow_liu(x)
    assert edge_set(tree) == edges
    assert tree.root == int(np.flatnonzero(parent == np.arange(15))[0])
    np.testing.assert_array_equal(tree.parent, parent)
    np.testing.assert_allclose(tree.p, p, atol=1e-12)
    np.testing.assert_allclose(tree.p_given_parent, a, atol=1e-12)
    np.testing.assert_allclose(tree.p_given_not_parent, b, atol=1e-12)


def test_same_tree_from_sparse_dense_and_lists():
    rng = np.random.default_rng(7)
    x = (rng.random((80, 25)) < 0.2).astype(np.int8)
    t_dense = fit_chow_liu(x)
    t_sparse = fit_chow_liu(sparse.csr_matrix(x))
    t_list = fit_chow_liu([np.flatnonzero(r) for r in x], 25)
    for t in (t_sparse, t_list):
        np.testing.assert_array_equal(t.parent, t_dense.parent)
        np.testing.assert_allclose(t.p_given_parent, t_dense.p_given_parent)


def test_always_spanning_even_with_unseen_and_isolated_words():
    # Words 5..9 never occur; 0-1 and 2-3 co-occur only with each other; dense pairs disabled.
    x = np.zeros((20, 10), np.int8)
    x[:10, 0] = x[:10, 1] = 1
    x[10:, 2] = x[10:, 3] = 1
    x[::3, 4] = 1
    tree = fit_chow_liu(x, dense_words=2)
    assert tree.size == 10  # ChowLiuTree validation guarantees one root and no cycle


def test_mutual_information_of_independent_words_is_small_and_dependent_large():
    n = 1000
    assert abs(mutual_information(250, 500, 500, n)) < 0.02
    assert mutual_information(500, 500, 500, n) > 0.5


def test_block_processing_gives_the_same_tree():
    rng = np.random.default_rng(11)
    x = (rng.random((300, 120)) < 0.08).astype(np.int8)
    whole = fit_chow_liu(x)
    blocked = fit_chow_liu(x, block_nnz=50)
    assert edge_set(whole) == edge_set(blocked)
