"""Same-word matching of binary descriptors, compiled (runtime/aefabmap_runtime/core/kernels/compiled.py).

`verification.match_keypoints` compares only keypoints that share a visual word. Its numpy
form builds every same-word pair, sorts them twice and gathers their descriptors: array-call
overhead per candidate place (docs/results.md, "Per frame"), paid for each of FAB-MAP's top
candidates on a frame that is not a revisit. This kernel
walks each query keypoint's word run among the place keypoints once and keeps the two smallest
Hamming distances as it goes. It returns the same matches, in the same order, ties broken the
same way (the numpy form is the reference the tests compare it with).
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.core.kernels import compiled, native
from aefabmap_runtime.core.kernels.bits import packed_words, popcount64_intrinsic


@compiled.kernel(native.same_word)
def same_word_kernel():
    """Mutual same-word nearest neighbours over uint64 descriptor words (see `match_same_word`).

    qw (N,) query words (negative: no word, skipped); qd (N, W) query rows; pw (M,) place words
    sorted ascending and order (M,) the place keypoint of each sorted entry (a stable sort, so a
    word's keypoints come in increasing index); pd (M, W) place rows; cap, ratio: float32 as the
    numpy form compares them; out (min(N, M), 2) receives the matches; returns their count.
    """
    popcount64 = popcount64_intrinsic()

    def same_word(qw, qd, pw, order, pd, cap, ratio, out):
        n, w = qd.shape
        m = pd.shape[0]
        # Per place keypoint: the closest query kept so far (the lower query index on a tie).
        best_d = np.full(m, np.int64(1) << 62, np.int64)
        best_q = np.full(m, -1, np.int64)
        for i in range(n):
            word = qw[i]
            if word < 0:
                continue
            lo = np.searchsorted(pw, word, side="left")
            hi = np.searchsorted(pw, word, side="right")
            if lo == hi:
                continue
            d1 = np.int64(1) << 62
            d2 = d1
            p1 = -1
            for k in range(lo, hi):
                j = order[k]
                d = np.int64(0)
                for b in range(w):
                    d += np.int64(popcount64(qd[i, b] ^ pd[j, b]))
                if d < d1:  # strict: the lower place index keeps a tie, as the stable sort does
                    d2, d1, p1 = d1, d, j
                elif d < d2:
                    d2 = d
            f1 = np.float32(d1)
            bar = ratio * np.float32(d2) if hi - lo > 1 else np.float32(np.inf)
            if f1 <= cap and f1 < bar and d1 < best_d[p1]:
                best_d[p1], best_q[p1] = d1, i
        count = 0
        for j in range(m):
            if best_q[j] >= 0:
                out[count, 0], out[count, 1] = best_q[j], j
                count += 1
        return count

    return compiled.numba.njit(
        "int64(int64[::1], uint64[:, ::1], int64[::1], int64[::1], uint64[:, ::1], float32, float32, int64[:, ::1])",
        nogil=True, cache=False, boundscheck=False)(same_word)


def match_same_word(q_words: np.ndarray, q_desc: np.ndarray, p_words: np.ndarray, p_desc: np.ndarray,
                    cap: float, ratio: float) -> np.ndarray:
    """(K, 2) int64 rows (query index, place index), sorted by place index: each query keypoint's
    nearest place keypoint of the same word by Hamming distance (the lower index on a tie) when
    it is within cap and closer than ratio times the second nearest of that word, then each place
    keypoint's closest such query (the lower query index on a tie).

    q_words (N,) / p_words (M,) int64 word ids (negative: no word); q_desc (N, B) / p_desc (M, B)
    uint8 packed bits. Compiled kernels only (`compiled.active() == "compiled"`).
    """
    order = np.argsort(p_words, kind="stable")
    out = np.empty((min(q_words.size, p_words.size), 2), np.int64)
    count = same_word_kernel()(
        np.ascontiguousarray(q_words, np.int64), packed_words(q_desc),
        np.ascontiguousarray(p_words[order], np.int64), order.astype(np.int64, copy=False), packed_words(p_desc),
        np.float32(cap), np.float32(ratio), out)
    return out[:count]
