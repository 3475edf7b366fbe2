"""Vocabulary tree training: exactly K leaves, seeded, leaves hold the training vectors they route."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.words.vocab_tree import VocabularyTree
from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans
from aefabmap_trainer.hierarchical_kmeans import _share_budget, fit_vocab_tree


def _bits(n: int, seed: int = 0) -> np.ndarray:
    """n 256-bit vectors around 12 random prototypes (10 % of bits flipped)."""
    rng = np.random.default_rng(seed)
    protos = rng.integers(0, 2, (12, 256))
    x = protos[rng.integers(0, 12, n)]
    flip = rng.random(x.shape) < 0.1
    return np.where(flip, 1 - x, x).astype(np.float32)


@pytest.mark.parametrize("words, branching", [(50, 4), (37, 10), (8, 8)])
def test_binary_tree_has_exactly_k_words_and_routes_training_vectors_to_their_leaf(words, branching):
    x = _bits(3000)
    a = fit_vocab_tree(x, words, branching, binary=True, config=KMeansConfig(8))
    assert a.words == words and a.leaf_counts.sum() == x.shape[0] and (a.leaf_counts > 0).all()
    assert a.centers.dtype == np.uint8 and a.centers.shape[1] == 32
    tree = VocabularyTree(a.centers, a.children, a.leaf_words)
    assert tree.vocabulary_size == words and tree.children.shape[1] == branching
    # The runtime routes every training vector the way training did: counts per word agree.
    w = tree.quantize_raw(np.packbits(x.astype(np.uint8), axis=1))
    assert np.array_equal(np.bincount(w, minlength=words), a.leaf_counts)


def test_float_tree_and_seeded_reproducibility():
    rng = np.random.default_rng(1)
    x = rng.random((2000, 16)).astype(np.float32)
    a = fit_vocab_tree(x, 40, 5, binary=False, config=KMeansConfig(6, seed=3))
    b = fit_vocab_tree(x, 40, 5, binary=False, config=KMeansConfig(6, seed=3))
    c = fit_vocab_tree(x, 40, 5, binary=False, config=KMeansConfig(6, seed=4))
    assert a.centers.dtype == np.float32 and a.words == 40
    for name in ("centers", "children", "leaf_words", "leaf_counts"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
    assert a.centers.tobytes() != c.centers.tobytes()


def test_k_majority_centroids_are_bits():
    x = _bits(1000)
    c = fit_kmeans(x, 6, KMeansConfig(5, binary=True))
    assert set(np.unique(c).tolist()) <= {0.0, 1.0}


def test_budget_is_shared_in_proportion_within_bounds():
    assert _share_budget(10, np.array([50, 30, 20])).tolist() == [5, 3, 2]
    s = _share_budget(10, np.array([1000, 1, 1]))
    assert s.tolist() == [8, 1, 1]
    assert _share_budget(5, np.array([1, 1, 10])).tolist() == [1, 1, 3]
    assert _share_budget(9, np.array([2, 3])).tolist() == [2, 3]  # fewer vectors than budget


def test_too_few_distinct_vectors_give_fewer_leaves_and_bad_settings_are_refused():
    x = np.repeat(np.eye(4, 256, dtype=np.float32), 10, axis=0)  # 4 distinct rows
    a = fit_vocab_tree(x, 8, 3, binary=True, config=KMeansConfig(4))
    assert a.words == 4
    with pytest.raises(ConfigError):
        fit_vocab_tree(x, 8, 1, binary=True)
    with pytest.raises(InputError):
        fit_vocab_tree(x[:5], 8, 3, binary=True)
    with pytest.raises(InputError, match="bit vectors"):
        fit_vocab_tree(x * 0.5, 4, 3, binary=True)
