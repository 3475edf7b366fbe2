"""tf-idf cosine bag-of-words scoring over an incremental inverted index (the BoW baseline). Pure."""

from __future__ import annotations

import numpy as np

from aefabmap.errors import InputError


class BowIndex:
    """Places as L2-normalised tf-idf vectors; a query's cosine similarity to every place.

    idf_q = log(M / df_q) from M training observations (df_q: observations holding word q;
    words never seen in training get log(M / 1)... i.e. the largest idf).
    """

    def __init__(self, vocabulary_size: int, training_observations) -> None:
        self.vocabulary_size = vocabulary_size
        df = np.zeros(vocabulary_size, np.int64)
        m = 0
        for obs in training_observations:
            w = np.unique(np.asarray(obs, np.int64))
            df[w] += 1
            m += 1
        if m == 0:
            raise InputError("BoW needs training observations for its idf weights")
        self.idf = np.log(m / np.maximum(df, 1)).astype(np.float64)
        self._ids: list[np.ndarray | None] = [None] * vocabulary_size
        self._wts: list[np.ndarray | None] = [None] * vocabulary_size
        self._len = np.zeros(vocabulary_size, np.int64)
        self.n_places = 0

    def vector(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Word ids with repeats (one per keypoint) -> (unique word ids, unit tf-idf weights)."""
        words = np.asarray(words, np.int64)
        if words.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        if words.min() < 0 or words.max() >= self.vocabulary_size:
            raise InputError(f"word ids must lie in [0, {self.vocabulary_size})")
        uniq, counts = np.unique(words, return_counts=True)
        w = counts / counts.sum() * self.idf[uniq]
        norm = np.linalg.norm(w)
        return uniq, (w / norm if norm > 0 else w)

    def add(self, words: np.ndarray) -> int:
        """Store a place from its word ids (with repeats); returns the place id."""
        uniq, wts = self.vector(words)
        pid = self.n_places
        for q, x in zip(uniq.tolist(), wts.tolist()):
            n = self._len[q]
            ids, ws = self._ids[q], self._wts[q]
            if ids is None:
                ids, ws = np.empty(4, np.intp), np.empty(4, np.float64)
            elif n == ids.size:
                ids = np.concatenate([ids, np.empty(n, np.intp)])
                ws = np.concatenate([ws, np.empty(n)])
            ids[n], ws[n] = pid, x
            self._ids[q], self._wts[q] = ids, ws
            self._len[q] = n + 1
        self.n_places += 1
        return pid

    def similarity(self, words: np.ndarray) -> np.ndarray:
        """Cosine similarity of the query (word ids with repeats) to every place, shape (n_places,)."""
        uniq, wts = self.vector(words)
        acc = np.zeros(self.n_places)
        for q, x in zip(uniq.tolist(), wts.tolist()):
            k = self._len[q]
            if k:
                acc[self._ids[q][:k]] += x * self._wts[q][:k]
        return acc
