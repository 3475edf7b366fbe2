"""tf-idf cosine bag-of-words scoring over an incremental inverted index (the BoW baseline). Pure."""

from __future__ import annotations

import numpy as np

from aefabmap.errors import InputError, StateError
from aefabmap.runtime.core.map_state import MapState, check_ptr, pack_ragged


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

    def state(self) -> MapState:
        """Postings (ids and tf-idf weights in their order, with buffer capacities), word lists, free ids."""
        st = MapState()
        n = self.n_places
        st.scalars.update(n_places=n, capacity=int(self._alive.size))
        st.arrays["alive"] = self._alive[:n].copy()
        st.arrays["words_ptr"], st.arrays["words"] = pack_ragged(self._words, self._word_dtype)
        st.arrays["post_cap"] = np.array([0 if b is None else b.size for b in self._ids], np.int64)
        rows = [None if b is None else b[:k] for b, k in zip(self._ids, self._len.tolist())]
        st.arrays["post_ptr"], st.arrays["postings"] = pack_ragged(rows, np.int64)
        wrows = [None if b is None else b[:k] for b, k in zip(self._wts, self._len.tolist())]
        st.arrays["weights"] = pack_ragged(wrows, np.float64)[1]
        st.arrays["free"] = np.array(self._free, np.int64)
        return st

    def load_state(self, st: MapState) -> None:
        """Replace the contents by a checked state (see state())."""
        v = self.vocabulary_size
        n = st.scalar("n_places", int, lo=0, hi=np.iinfo(np.int32).max)
        cap = st.scalar("capacity", int, lo=n, hi=max(64, 2 * n) + 1)
        alive = st.array("alive", "b", (n,))
        words = st.array("words", "iu", (None,), lo=0, hi=v)
        wptr = check_ptr(st, "words_ptr", n, words.size)
        post_cap = st.array("post_cap", "iu", (v,), lo=0)
        postings = st.array("postings", "iu", (None,), lo=0, hi=max(n, 1))
        weights = st.array("weights", "f", (postings.size,))
        pptr = check_ptr(st, "post_ptr", v, postings.size)
        free = st.array("free", "iu", (None,), lo=0, hi=max(n, 1))
        lens, rows = np.diff(pptr), np.diff(wptr)
        if np.any(rows[~alive] != 0):
            raise StateError("map state: a removed place still has words")
        if np.any(lens > post_cap) or np.any((post_cap == 0) != (lens == 0)) or np.any(post_cap > 8 * lens + 8):
            raise StateError("map state: posting capacities do not fit their lengths")
        if np.any(weights < 0) or np.any(weights > 1):
            raise StateError("map state: tf-idf weights outside [0, 1]")
        if np.unique(free).size != free.size or set(free.tolist()) != set(np.flatnonzero(~alive).tolist()):
            raise StateError("map state: free ids are not exactly the removed places")
        place_of = np.repeat(np.arange(n, dtype=np.int64), rows)
        if words.size > 1:
            same = place_of[1:] == place_of[:-1]
            if np.any(words[1:][same] <= words[:-1][same]):
                raise StateError("map state: a place's word ids are not sorted and unique")
        word_of = np.repeat(np.arange(v, dtype=np.int64), lens)
        a, b = np.lexsort((place_of, words)), np.lexsort((postings, word_of))
        if words.size != postings.size or np.any(words[a] != word_of[b]) or np.any(place_of[a] != postings[b]):
            raise StateError("map state: postings do not match the places' words")
        self.n_places, self.n_alive = n, int(alive.sum())
        self._alive = np.zeros(cap, bool)
        self._alive[:n] = alive
        self._words = [None] * n
        self._buffer_bytes = 0
        for pid in np.flatnonzero(alive).tolist():
            self._words[pid] = words[wptr[pid]:wptr[pid + 1]].astype(self._word_dtype)
            self._buffer_bytes += self._words[pid].nbytes
        self._ids, self._wts = [None] * v, [None] * v
        self._len = lens.astype(np.int64)
        for q in np.flatnonzero(post_cap).tolist():
            c, k = int(post_cap[q]), int(lens[q])
            ids, ws = np.empty(c, np.intp), np.empty(c, np.float64)
            ids[:k], ws[:k] = postings[pptr[q]:pptr[q + 1]], weights[pptr[q]:pptr[q + 1]]
            self._ids[q], self._wts[q] = ids, ws
            self._buffer_bytes += ids.nbytes + ws.nbytes
        self._free = free.tolist()

    def nbytes(self) -> int:
        """Bytes held by posting lists, per-place word lists and per-place arrays (O(1))."""
        # 8 bytes per list slot of self._words, plus the fixed per-word length array.
        return int(self._buffer_bytes + self._alive.nbytes + 8 * len(self._words) + self._len.nbytes)
