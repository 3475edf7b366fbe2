"""k-means vocabulary: deterministic, finds real clusters, refuses bad sizes."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap import ConfigError, InputError
from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer
from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans


def blobs(seed=0, k=5, per=200, d=16):
    rng = np.random.default_rng(seed)
    centres = rng.normal(0, 10, (k, d))
    x = np.concatenate([c + rng.normal(0, 0.5, (per, d)) for c in centres]).astype(np.float32)
    return x, np.repeat(np.arange(k), per)


def test_recovers_separated_clusters():
    x, truth = blobs()
    c = fit_kmeans(x, 5, KMeansConfig(seed=1))
    words = NearestCentroidQuantizer(c).quantize(x)
    # Each true cluster maps to exactly one word and vice versa.
    pairs = set(zip(truth.tolist(), words.tolist()))
    assert len(pairs) == 5 and len({w for _, w in pairs}) == 5


def test_deterministic_with_seed():
    x, _ = blobs(2)
    a = fit_kmeans(x, 8, KMeansConfig(seed=3))
    b = fit_kmeans(x, 8, KMeansConfig(seed=3))
    np.testing.assert_array_equal(a, b)


def test_binary_vectors_and_hamming():
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2, (400, 256)).astype(np.float32)
    c = fit_kmeans(bits, 10, KMeansConfig(max_iterations=5))
    q = NearestCentroidQuantizer(c)
    brute = np.argmin(((bits[:, None, :] - c[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(q.quantize(bits), brute)


def test_bad_sizes():
    x, _ = blobs()
    with pytest.raises(ConfigError):
        fit_kmeans(x, 1)
    with pytest.raises(InputError, match="at least k"):
        fit_kmeans(x[:3], 5)
    with pytest.raises(InputError, match="distinct"):
        fit_kmeans(np.zeros((50, 4), np.float32), 5)
    with pytest.raises(InputError, match="shape"):
        NearestCentroidQuantizer(x[:5]).quantize(np.zeros((3, 7), np.float32))
