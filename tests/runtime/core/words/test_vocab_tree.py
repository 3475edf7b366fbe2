"""Vocabulary tree quantiser: descent = brute force where it must be, validation."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.kernels.bits import hamming
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer, quantize_raw
from aefabmap_runtime.core.words.vocab_tree import VocabularyTree, tree_depth, validate_tree


def _one_level(centers: np.ndarray) -> VocabularyTree:
    """Root with every word as a direct child: the descent is a brute-force search."""
    k = centers.shape[0]
    root = np.zeros((1, centers.shape[1]), centers.dtype)
    children = np.full((k + 1, k), -1, np.int32)
    children[0] = np.arange(1, k + 1)
    words = np.concatenate([[-1], np.arange(k)]).astype(np.int32)
    return VocabularyTree(np.vstack([root, centers]), children, words)


def test_single_level_binary_tree_is_brute_force_hamming():
    rng = np.random.default_rng(2)
    centers = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    x = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    tree = _one_level(centers)
    expect = np.argmin(hamming(centers[None], x[:, None]), axis=1)
    assert np.array_equal(tree.quantize_raw(x), expect)
    # Flat nearest centroid on unpacked bits with the same 0/1 centres: squared L2 = Hamming.
    flat = NearestCentroidQuantizer(np.unpackbits(centers, axis=1).astype(np.float32))
    kind = get_kind("orb")
    assert np.array_equal(flat.quantize(kind.vectors(x)), expect)
    assert np.array_equal(quantize_raw(tree, kind, x), expect)
    assert np.array_equal(tree.quantize(kind.vectors(x)), expect)


def test_single_level_float_tree_is_brute_force_l2():
    rng = np.random.default_rng(3)
    centers = rng.random((30, 16)).astype(np.float32)
    x = rng.random((200, 16)).astype(np.float32)
    tree = _one_level(centers)
    assert not tree.accepts_packed_bits
    expect = np.argmin(((x[:, None] - centers[None]) ** 2).sum(-1), axis=1)
    assert np.array_equal(tree.quantize(x), expect)


def test_two_level_tree_on_separated_clusters_matches_brute_force():
    """Four groups of words far apart in Hamming space (bytes 0-7 set per group): greedy descent
    picks the right group, then the right word, so the tree equals brute force over the leaves."""
    rng = np.random.default_rng(4)
    groups, per = 4, 5
    leaves, parents = [], []
    for g in range(groups):
        base = np.zeros(32, np.uint8)
        base[8 * g : 8 * g + 8] = 255
        parents.append(base)
        for _ in range(per):
            w = base.copy()
            w[8 * g + rng.integers(0, 8)] ^= np.uint8(1 << rng.integers(0, 8))  # 1 bit off the group
            w[(8 * g + 8 + rng.integers(0, 24)) % 32] |= np.uint8(1 << rng.integers(0, 8))
            leaves.append(w)
    leaves = np.unique(np.array(leaves), axis=0)
    # Rebuild groups from the unique leaves (a duplicate may have collapsed).
    group_of = np.array([np.argmax([np.unpackbits(l[8 * g:8 * g + 8]).sum() for g in range(groups)]) for l in leaves])
    m = 1 + groups + len(leaves)
    centers = np.zeros((m, 32), np.uint8)
    children = np.full((m, max(groups, per + 1)), -1, np.int32)
    words = np.full(m, -1, np.int32)
    centers[1 : 1 + groups] = parents
    children[0, :groups] = np.arange(1, 1 + groups)
    nxt = 1 + groups
    order = []
    for g in range(groups):
        mine = np.flatnonzero(group_of == g)
        children[1 + g, : mine.size] = np.arange(nxt, nxt + mine.size)
        centers[nxt : nxt + mine.size] = leaves[mine]
        order.extend(mine)
        nxt += mine.size
    words[1 + groups :] = np.arange(len(leaves))
    tree = VocabularyTree(centers, children, words)
    assert tree.depth == 2 and tree.vocabulary_size == len(leaves)
    leaf_centers = leaves[np.array(order)]  # word w has centre leaf_centers[w]
    x = leaf_centers[rng.integers(0, len(leaves), 500)].copy()
    flip = rng.integers(0, 256, 500)
    x[np.arange(500), flip // 8] ^= (1 << (flip % 8)).astype(np.uint8)  # one bit of noise
    expect = np.argmin(hamming(leaf_centers[None], x[:, None]), axis=1)
    assert np.array_equal(tree.quantize_raw(x), expect)


def test_descriptors_of_the_wrong_form_are_refused():
    tree = _one_level(np.random.default_rng(5).integers(0, 256, (4, 32), dtype=np.uint8))
    with pytest.raises(InputError):
        tree.quantize_raw(np.zeros((3, 31), np.uint8))
    with pytest.raises(InputError):
        tree.quantize_raw(np.zeros((3, 32), np.float32))
    with pytest.raises(InputError):
        tree.quantize(np.zeros((3, 32), np.float32))  # vectors are 256 bits, not 32 bytes
    assert tree.quantize_raw(np.zeros((0, 32), np.uint8)).shape == (0,)


def _valid():
    centers = np.zeros((5, 4), np.uint8)
    children = np.array([[1, 2], [3, 4], [-1, -1], [-1, -1], [-1, -1]], np.int32)
    words = np.array([-1, -1, 0, 1, 2], np.int32)
    return centers, children, words


def test_valid_tree_passes_and_has_its_depth():
    c, ch, w = _valid()
    validate_tree(c, ch, w)
    assert tree_depth(ch) == 2


@pytest.mark.parametrize(
    "break_it, message",
    [
        (lambda c, ch, w: ch.__setitem__((1, 0), 0), "numbered after their parent"),   # a cycle to the root
        (lambda c, ch, w: ch.__setitem__((1, 0), 9), r"node ids in \[0, 5\)"),
        (lambda c, ch, w: ch.__setitem__((1, 0), -7), r"node ids in \[0, 5\)"),
        (lambda c, ch, w: ch.__setitem__((1, 1), 2), "exactly one parent"),             # 2 has two parents
        (lambda c, ch, w: ch.__setitem__((1, slice(None)), [-1, 3]), "padding must come after"),
        (lambda c, ch, w: w.__setitem__(4, 0), "word ids 0..2"),                        # word 0 twice
        (lambda c, ch, w: w.__setitem__(1, 7), "inner tree nodes must have leaf word -1"),
    ],
)
def test_broken_trees_are_refused(break_it, message):
    c, ch, w = _valid()
    break_it(c, ch, w)
    with pytest.raises(InputError, match=message):
        validate_tree(c, ch, w)


def test_single_child_and_bad_centres_are_refused():
    c = np.zeros((4, 4), np.uint8)
    ch = np.array([[1, 2], [3, -1], [-1, -1], [-1, -1]], np.int32)
    w = np.array([-1, -1, 0, 1], np.int32)
    with pytest.raises(InputError, match="at least 2 children"):
        validate_tree(c, ch, w)
    c2, ch2, w2 = _valid()
    bad = c2.astype(np.float32)
    bad[3, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        validate_tree(bad, ch2, w2)
    with pytest.raises(InputError, match="uint8 .* or float32"):
        validate_tree(c2.astype(np.int64), ch2, w2)
