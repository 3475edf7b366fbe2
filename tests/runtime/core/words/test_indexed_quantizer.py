"""Flat vocabulary behind an inverted index: same words as the exhaustive search where it must be."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.words.quantizer import IndexedCentroidQuantizer, NearestCentroidQuantizer, quantize_raw, validate_index
from aefabmap_trainer.centroid_index import build_lists, fit_routing
from aefabmap_trainer.kmeans import KMeansConfig


def _bits(n, seed):
    return (np.random.default_rng(seed).random((n, 256)) < 0.5).astype(np.float32)


@pytest.mark.parametrize("buckets", [1, 4, 16])
def test_index_reproduces_the_flat_words_on_the_vectors_it_was_built_from(buckets):
    x = _bits(4000, 0)
    centroids = np.random.default_rng(1).random((60, 256)).astype(np.float32)
    flat = NearestCentroidQuantizer(centroids)
    words = flat.quantize(x)
    centers = fit_routing(x, buckets, binary=True, config=KMeansConfig(5))
    indptr, listed = build_lists(centers, centroids, [(x[:2000], words[:2000]), (x[2000:], words[2000:])])
    q = IndexedCentroidQuantizer(centroids, centers, indptr, listed)
    assert q.accepts_packed_bits and q.buckets == buckets
    assert np.array_equal(q.quantize(x), words)
    packed = np.packbits(x.astype(np.uint8), axis=1)
    assert np.array_equal(quantize_raw(q, get_kind("orb"), packed), words)
    if buckets == 1:  # one bucket holding every word: the exhaustive search itself
        assert listed.size == 60
        y = _bits(500, 2)
        assert np.array_equal(q.quantize(y), flat.quantize(y))


def test_float_routing_for_float_vectors():
    rng = np.random.default_rng(3)
    x = rng.random((3000, 16)).astype(np.float32)
    centroids = rng.random((40, 16)).astype(np.float32)
    flat = NearestCentroidQuantizer(centroids)
    centers = fit_routing(x, 6, binary=False, config=KMeansConfig(5))
    indptr, listed = build_lists(centers, centroids, [(x, flat.quantize(x))])
    q = IndexedCentroidQuantizer(centroids, centers, indptr, listed)
    assert not q.accepts_packed_bits and centers.dtype == np.float32
    assert np.array_equal(q.quantize(x), flat.quantize(x))
    with pytest.raises(InputError):
        q.quantize_raw(np.zeros((2, 2), np.uint8))


def _index():
    centers = np.zeros((2, 32), np.uint8)
    return centers, np.array([0, 2, 3]), np.array([0, 1, 2], np.int32)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c, p, w: (c, np.array([0, 2, 4]), w), "end at len"),
        (lambda c, p, w: (c, np.array([0, 3, 3]), w), "grow by >= 1"),
        (lambda c, p, w: (c, p, np.array([0, 1, 5], np.int32)), r"word ids in \[0, 3\)"),
        (lambda c, p, w: (c, p, np.array([0, 0, 2], np.int32)), "repeat within a bucket"),
        (lambda c, p, w: (c, np.array([0, 1, 3]), np.array([0, 1, 0], np.int32)), "every word"),
        (lambda c, p, w: (np.zeros((2, 31), np.uint8), p, w), r"\(S, 32\)"),
        (lambda c, p, w: (c.astype(np.int16), p, w), "uint8 or float32"),
        (lambda c, p, w: (c, np.array([0, 2]), w), r"\(3,\) integers"),
    ],
)
def test_broken_indexes_are_refused(edit, message):
    c, p, w = edit(*_index())
    with pytest.raises(InputError, match=message):
        validate_index(c, p, w, 3, 256)
