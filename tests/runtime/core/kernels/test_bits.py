"""Popcount, Hamming distance and nearest neighbours of packed bits: every path against unpacked bits."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.kernels.bits import POPCOUNT_TABLE, hamming, nearest_two, popcount_rows


@pytest.mark.parametrize("width", [1, 7, 8, 32, 61])
@pytest.mark.parametrize("use_table", [False, True])
def test_popcount_counts_the_set_bits(width, use_table):
    rng = np.random.default_rng(width)
    x = rng.integers(0, 256, (50, 3, width), dtype=np.uint8)
    x[0, 0] = 255  # every bit set: 8 * width, no overflow of a narrow accumulator
    expect = np.unpackbits(x, axis=-1).sum(axis=-1)
    got = popcount_rows(x, use_table=use_table)
    assert got.dtype == np.int32 and np.array_equal(got, expect)
    assert got[0, 0] == 8 * width


def test_popcount_table_and_hamming_against_unpacked_bits():
    assert [int(POPCOUNT_TABLE[v]) for v in (0, 1, 3, 128, 255)] == [0, 1, 2, 1, 8]
    rng = np.random.default_rng(1)
    a, b = rng.integers(0, 256, (2, 200, 32), dtype=np.uint8)
    expect = (np.unpackbits(a, axis=1) != np.unpackbits(b, axis=1)).sum(axis=1)
    assert np.array_equal(hamming(a, b), expect)


def test_hamming_broadcasts_and_refuses_other_dtypes():
    rng = np.random.default_rng(2)
    a, b = rng.integers(0, 256, (7, 32), dtype=np.uint8), rng.integers(0, 256, (5, 32), dtype=np.uint8)
    table = hamming(a[:, None, :], b[None, :, :])
    assert table.shape == (7, 5)
    assert table[3, 4] == (np.unpackbits(a[3]) != np.unpackbits(b[4])).sum()
    with pytest.raises(InputError):
        popcount_rows(a.astype(np.int16))


def _nearest_two_by_unpacked_bits(a, b):
    """Reference: full distance matrix from unpacked bits, two smallest per row (stable: lower index on a tie)."""
    d = (np.unpackbits(a, axis=1)[:, None, :] != np.unpackbits(b, axis=1)[None, :, :]).sum(axis=2)
    order = np.argsort(d, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(d, order, axis=1), order


@pytest.mark.parametrize("width", [32, 61, 64, 8])
def test_nearest_two_equals_the_full_distance_matrix_ties_included(width, kernels):
    """Both paths (compiled kernel, OpenCV) give the same neighbours, the lower index winning a
    tie: bytes drawn from {0..3} make most distances tie."""
    rng = np.random.default_rng(width)
    a = rng.integers(0, 4, (120, width), dtype=np.uint8)
    b = rng.integers(0, 4, (90, width), dtype=np.uint8)
    dist, index = nearest_two(a, b)
    # Fewer than two rows to search: the missing neighbour is (-1, 2^31 - 1).
    d1, i1 = nearest_two(a[:3], b[:1])
    d0, i0 = nearest_two(a[:0], b)
    expect_d, expect_i = _nearest_two_by_unpacked_bits(a, b)
    assert dist.dtype == np.int32 and index.dtype == np.int32
    assert np.array_equal(dist, expect_d) and np.array_equal(index, expect_i)
    assert np.array_equal(i1[:, 0], [0, 0, 0]) and np.all(i1[:, 1] == -1) and np.all(d1[:, 1] == 2**31 - 1)
    assert np.array_equal(d1[:, 0], _nearest_two_by_unpacked_bits(a[:3], b[:1])[0][:, 0])
    assert d0.shape == (0, 2) and i0.shape == (0, 2)


@pytest.mark.parametrize("rows", [2, 3, 4, 5, 6, 7, 8, 9, 12, 1001])
def test_nearest_two_of_orb_rows_for_every_count_of_searched_rows(rows, kernels):
    """ORB's 32 bytes take the compiled kernel's four-rows-a-step path, whose per-lane minima and
    leftover rows must give the reference's neighbours whatever the number of searched rows."""
    rng = np.random.default_rng(rows)
    a = rng.integers(0, 4, (40, 32), dtype=np.uint8)
    b = rng.integers(0, 4, (rows, 32), dtype=np.uint8)
    a[0], b[-1] = 255, 0  # all 256 bits apart: the largest distance a vector lane sums
    dist, index = nearest_two(a, b)
    expect_d, expect_i = _nearest_two_by_unpacked_bits(a, b)
    assert np.array_equal(dist, expect_d) and np.array_equal(index, expect_i)


def test_nearest_two_rejects_rows_it_cannot_compare():
    a = np.zeros((3, 32), np.uint8)
    for bad in (np.zeros((3, 31), np.uint8), np.zeros((3, 32), np.float32), np.zeros(32, np.uint8)):
        with pytest.raises(InputError):
            nearest_two(a, bad)
