"""Popcount and Hamming distance of packed bits: every path against unpacked bits."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap.errors import InputError
from aefabmap.runtime.core.bits import POPCOUNT_TABLE, hamming, popcount_rows


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
