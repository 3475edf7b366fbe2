"""Two nearest neighbours for the brute-force retry: the matrix-product L2 path against direct
distances, and the Hamming path's conversion of missing neighbours."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.verify.nearest import ROWS, nearest_two, unit_rows


def _direct_l2(q, p):
    """Reference: every distance of unit rows in float64, two smallest per row (lower index on a tie)."""
    qu, pu = unit_rows(q).astype(np.float64), unit_rows(p).astype(np.float64)
    d = np.sqrt(((qu[:, None, :] - pu[None, :, :]) ** 2).sum(axis=2))
    order = np.argsort(d, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(d, order, axis=1), order


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
def test_l2_neighbours_equal_direct_distances_across_row_blocks(dtype):
    rng = np.random.default_rng(3)
    n = ROWS + 37  # two blocks of the matrix product
    p = (rng.random((300, 128)) * 255).astype(dtype)
    q = p[rng.integers(0, 300, n)].astype(np.float64) + rng.normal(0, 8, (n, 128))
    q = np.clip(q, 0, 255).astype(dtype)  # near copies: a clear nearest, then a far second
    dist, index = nearest_two(q, p, "l2")
    expect_d, expect_i = _direct_l2(q, p)
    assert dist.dtype == np.float32 and index.dtype == np.int64
    assert np.array_equal(index, expect_i)
    np.testing.assert_allclose(dist, expect_d, atol=2e-3)


def test_fewer_than_two_rows_leave_the_second_neighbour_missing():
    rng = np.random.default_rng(4)
    q, p = rng.random((5, 16), dtype=np.float32), rng.random((1, 16), dtype=np.float32)
    for distance, (a, b) in (("l2", (q, p)), ("hamming", ((q * 255).astype(np.uint8), (p * 255).astype(np.uint8)))):
        dist, index = nearest_two(a, b, distance)
        assert np.all(index[:, 0] == 0) and np.all(index[:, 1] == -1)
        assert np.all(np.isfinite(dist[:, 0])) and np.all(np.isinf(dist[:, 1]))
        dist, index = nearest_two(a, b[:0], distance)
        assert np.all(index == -1) and np.all(np.isinf(dist))


def test_hamming_distances_are_bit_counts():
    rng = np.random.default_rng(5)
    q, p = rng.integers(0, 256, (40, 32), dtype=np.uint8), rng.integers(0, 256, (30, 32), dtype=np.uint8)
    dist, index = nearest_two(q, p, "hamming")
    bits = (np.unpackbits(q, axis=1)[:, None] != np.unpackbits(p, axis=1)[None]).sum(axis=2)
    assert np.array_equal(dist, np.sort(bits, axis=1)[:, :2].astype(np.float32))
    assert np.array_equal(bits[np.arange(40), index[:, 0]], bits.min(axis=1))


def test_rejects_unknown_distances_and_mismatched_rows():
    a = np.zeros((3, 8), np.float32)
    with pytest.raises(ConfigError):
        nearest_two(a, a, "cosine")
    with pytest.raises(InputError):
        nearest_two(a, np.zeros((3, 9), np.float32), "l2")
