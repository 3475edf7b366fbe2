"""The scatter behind FAB-MAP scoring: numpy and compiled paths equal the per-word loop bit for bit."""

import numpy as np

from aefabmap_runtime.core.rank.scatter import scatter_scores


def _case(seed: int, n: int = 500, words: int = 60):
    rng = np.random.default_rng(seed)
    lens = rng.integers(0, n // 3, words).astype(np.int64)
    rows = [np.sort(rng.choice(n, k, replace=False)).astype(np.int32) for k in lens]
    weights = rng.standard_normal(words) * 10.0 ** rng.integers(-3, 4, words)
    defaults = rng.standard_normal(n) * 100.0
    return defaults, rows, weights, lens


def _reference(defaults, rows, weights):
    acc = defaults.copy()
    for r, w in zip(rows, weights.tolist()):
        acc[r.astype(np.intp)] += w
    return acc


def test_scatter_matches_per_word_adds_exactly(kernels):
    for seed in range(5):
        defaults, rows, weights, lens = _case(seed)
        got = scatter_scores(defaults, rows, weights, lens)
        np.testing.assert_array_equal(got, _reference(defaults, rows, weights))
    # No postings at all: the defaults, as a copy.
    d = np.arange(4.0)
    out = scatter_scores(d, [], np.zeros(0), np.zeros(0, np.int64))
    np.testing.assert_array_equal(out, d)
    assert out is not d
