"""tf-idf cosine bag-of-words scoring over an incremental inverted index (the BoW baseline). Pure."""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.core.rank.postings import PostingLists, PostingsView


class BowIndex(PostingsView):
    """Places as L2-normalised tf-idf vectors; a query's cosine similarity to every place.

    idf_q = log(M / df_q) from M training observations (df_q: observations holding word q;
    words never seen in training get log(M / 1)... i.e. the largest idf).
    Places can be removed (bounded-memory maps): their postings leave the word lists and their
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
        self.postings = PostingLists(vocabulary_size, weighted=True)

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
        return self.postings.add(uniq, wts)

    def remove(self, pid: int) -> None:
        """Forget a place (PostingLists.remove)."""
        self.postings.remove(pid)

    def similarity(self, words: np.ndarray) -> np.ndarray:
        """Cosine similarity of the query (word ids with repeats) to every place id, shape (n_places,).

        Removed ids score 0.
        """
        uniq, wts = self.vector(words)
        acc = np.zeros(self.n_places)
        for q, x in zip(uniq.tolist(), wts.tolist()):
            ids = self.postings.ids(q)
            if ids.size:
                acc[ids] += x * self.postings.weights(q)
        return acc

    def state(self) -> MapState:
        """Postings (ids and tf-idf weights in their order, with buffer capacities), word lists, free ids."""
        return self.postings.state()

    def load_state(self, st: MapState) -> None:
        """Replace the contents by a checked state (see state()); tf-idf weights lie in [0, 1]."""
        self.postings.load_state(st, weight_range=(0.0, 1.0))

    def nbytes(self) -> int:
        """Bytes held by posting lists, per-place word lists and per-place arrays (O(1))."""
        return self.postings.nbytes()
