"""tf-idf cosine bag-of-words scoring over an incremental inverted index (the BoW baseline). Pure."""

from __future__ import annotations

import numpy as np

from aefabmap.errors import InputError


class BowIndex:
    """Places as L2-normalised tf-idf vectors; a query's cosine similarity to every place.

    idf_q = log(M / df_q) from M training observations (df_q: observations holding word q;
    words never seen in training get log(M / 1)... i.e. the largest idf).
    Places can be removed (bounded-memory maps): their postings are compacted out and their
    id is reused by a later add(), so the id range stays bounded under evict-and-add.
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
        self._alive = np.zeros(0, bool)
        self._words: list[np.ndarray | None] = []  # each place's word ids, for removal
        self._word_dtype = np.uint16 if vocabulary_size <= 65536 else np.uint32
        self._free: list[int] = []  # removed ids, reused first
        self._buffer_bytes = 0  # posting buffers and word lists, kept up to date
        self.n_places = 0  # size of the id range (removed ids included)
        self.n_alive = 0

    @property
    def alive(self) -> np.ndarray:
        """(n_places,) bool: which ids hold a place."""
        return self._alive[: self.n_places]

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
        pid = self._free.pop() if self._free else self.n_places
        if pid >= self._alive.size:
            self._alive = np.concatenate([self._alive, np.zeros(max(64, self._alive.size), bool)])
        for q, x in zip(uniq.tolist(), wts.tolist()):
            n = self._len[q]
            ids, ws = self._ids[q], self._wts[q]
            if ids is None:
                ids, ws = np.empty(4, np.intp), np.empty(4, np.float64)
                self._buffer_bytes += ids.nbytes + ws.nbytes
            elif n == ids.size:
                ids = np.concatenate([ids, np.empty(n, np.intp)])
                ws = np.concatenate([ws, np.empty(n)])
                self._buffer_bytes += ids.nbytes // 2 + ws.nbytes // 2
            ids[n], ws[n] = pid, x
            self._ids[q], self._wts[q] = ids, ws
            self._len[q] = n + 1
        stored = uniq.astype(self._word_dtype)
        self._buffer_bytes += stored.nbytes
        if pid == self.n_places:
            self._words.append(stored)
            self.n_places += 1
        else:
            self._words[pid] = stored
        self._alive[pid] = True
        self.n_alive += 1
        return pid

    def remove(self, pid: int) -> None:
        """Forget a place: its postings leave each of its words' lists (order kept)."""
        if not (0 <= pid < self.n_places) or not self._alive[pid]:
            raise InputError(f"place {pid} is not in the index")
        for q in self._words[pid].tolist():
            n = self._len[q]
            ids, ws = self._ids[q], self._wts[q]
            keep = ids[:n] != pid
            k = int(keep.sum())
            ids[:k], ws[:k] = ids[:n][keep], ws[:n][keep]
            self._len[q] = k
            if k == 0:
                self._buffer_bytes -= ids.nbytes + ws.nbytes
                self._ids[q] = self._wts[q] = None
            elif k * 4 <= ids.size and ids.size > 8:
                # Shrink a list that lost most of its postings, keeping room to grow.
                size = max(4, 2 * k)
                self._buffer_bytes -= (ids.size - size) * (ids.itemsize + ws.itemsize)
                self._ids[q], self._wts[q] = ids[:size].copy(), ws[:size].copy()
        self._buffer_bytes -= self._words[pid].nbytes
        self._words[pid] = None
        self._alive[pid] = False
        self._free.append(pid)
        self.n_alive -= 1

    def similarity(self, words: np.ndarray) -> np.ndarray:
        """Cosine similarity of the query (word ids with repeats) to every place id, shape (n_places,).

        Removed ids score 0.
        """
        uniq, wts = self.vector(words)
        acc = np.zeros(self.n_places)
        for q, x in zip(uniq.tolist(), wts.tolist()):
            k = self._len[q]
            if k:
                acc[self._ids[q][:k]] += x * self._wts[q][:k]
        return acc

    def nbytes(self) -> int:
        """Bytes held by posting lists, per-place word lists and per-place arrays (O(1))."""
        # 8 bytes per list slot of self._words, plus the fixed per-word length array.
        return int(self._buffer_bytes + self._alive.nbytes + 8 * len(self._words) + self._len.nbytes)
