"""The compiled same-word matcher gives the numpy matcher's matches exactly (runtime/aefabmap_runtime/core/verify/word_matches.py)."""

import numpy as np
import pytest

from aefabmap_runtime.core.verify.verification import NO_WORD, VerificationConfig, match_keypoints


def _matches(q_words, q_desc, p_words, p_desc, config=None):
    """A call of the same-word matcher on binary descriptors, to run on both paths."""
    return lambda: match_keypoints(q_words, q_desc, p_words, p_desc, config or VerificationConfig(), distance="hamming")


@pytest.mark.parametrize("width", [32, 61, 8])  # ORB, AKAZE (not a whole number of 64-bit words), 64 bits
@pytest.mark.parametrize("seed", range(6))
def test_compiled_same_word_matches_equal_the_numpy_ones(width, seed, on_both_paths):
    rng = np.random.default_rng(seed)
    n, m, vocabulary = 300, 400, 40  # ~10 place keypoints per word: ratio tests and mutual conflicts
    # Few distinct base descriptors, lightly perturbed: many equal distances (ties) and near misses.
    base = rng.integers(0, 256, (25, width), dtype=np.uint8)
    flip = lambda k: np.where(rng.random((k, width)) < 0.05, rng.integers(0, 256, (k, width)), 0).astype(np.uint8)
    q_desc = base[rng.integers(0, 25, n)] ^ flip(n)
    p_desc = base[rng.integers(0, 25, m)] ^ flip(m)
    q_words = rng.integers(0, vocabulary, n)
    p_words = rng.integers(0, vocabulary, m)
    q_words[rng.random(n) < 0.2] = NO_WORD  # keypoints beyond the bundle's budget carry no word
    p_words[rng.random(m) < 0.2] = NO_WORD
    for ratio, max_hamming in ((0.9, 64), (1.0, 256), (0.8, 20), (0.75, 64)):
        config = VerificationConfig(ratio=ratio, max_hamming=max_hamming)
        slow, fast = on_both_paths(_matches(q_words, q_desc, p_words, p_desc, config))
        assert fast.dtype == np.int64 and fast.shape[1] == 2
        np.testing.assert_array_equal(fast, slow)
    assert len(slow) > 0


def test_compiled_same_word_matching_of_empty_and_unworded_frames(on_both_paths):
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    none = np.full(5, NO_WORD)
    for q_words, p_words in ((none, none), (np.arange(5), none), (none, np.arange(5)), (np.arange(5), np.arange(5) + 5)):
        slow, fast = on_both_paths(_matches(q_words, d, p_words, d))
        assert fast.shape == slow.shape == (0, 2)
    slow, fast = on_both_paths(_matches(np.zeros(0, np.int64), d[:0], np.arange(5), d))
    assert fast.shape == slow.shape == (0, 2)
