"""Word -> place postings that grow, shrink and reuse place ids: the inverted index that both
scorers (FAB-MAP's InvertedIndex, the BoW baseline's BowIndex) keep. Pure.

A posting is a place id (int32), optionally with a float64 weight (BoW's tf-idf). Each word
has its own growable buffer, so adding a place costs its words, not the map. Each place keeps
its sorted word ids (uint16 when V <= 65536) so that removing it costs its words too; removed
ids are reused first, so the id range stays bounded when a capped map keeps evicting and adding.
The data address of every word's buffer is kept beside it, so the compiled scatter
(runtime/aefabmap_runtime/core/rank/scatter.py) reads a query's postings where they lie instead of copying them end
to end first.
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.errors import InputError, StateError
from aefabmap_runtime.core.kernels import compiled
from aefabmap_runtime.core.rank import scatter
from aefabmap_runtime.core.records.map_state import MapState, check_ptr, pack_ragged


def grown(n: int) -> int:
    """Next capacity of a full posting buffer of n entries: +25 % keeps the mean slack far below
    doubling's (docs/results.md, "Memory"), at the price of more (memcpy-cheap) regrowths."""
    return n + max(4, n >> 2)


class PostingLists:
    """Per-word posting buffers, per-place word lists and the free-id list.

    weighted: every posting also holds a float64 weight, given per word to `add`.
    `capacity` is the length of the per-place arrays; owners with per-place arrays of their own
    grow them to it after `add`.
    """

    def __init__(self, vocabulary_size: int, *, weighted: bool = False) -> None:
        self.vocabulary_size = vocabulary_size
        self.weighted = weighted
        self._ids: list[np.ndarray | None] = [None] * vocabulary_size
        # Data address of each _ids[q] (0: none), for the compiled scatter; refreshed on demand
        # (`addresses`) for the words whose buffer changed since (`_stale`), so the numpy path,
        # which never asks, pays nothing for it.
        self._addr = np.zeros(vocabulary_size, np.intp)
        self._stale = np.zeros(vocabulary_size, bool)
        self._cap = np.zeros(vocabulary_size, np.int32)  # size of each _ids[q] (0: none)
        self._wts: list[np.ndarray | None] = [None] * vocabulary_size if weighted else []
        self._len = np.zeros(vocabulary_size, np.int32)  # postings per word (< 2^31: one per place)
        self._alive = np.zeros(0, bool)
        self._words: list[np.ndarray | None] = []  # each place's word ids, for removal
        self._word_dtype = np.uint16 if vocabulary_size <= 65536 else np.uint32
        self._free: list[int] = []  # removed ids, reused first
        self._buffer_bytes = 0  # posting buffers and word lists, kept up to date
        self.n_places = 0  # size of the id range (removed ids included)
        self.n_alive = 0
        if not weighted:  # weighted lists always take the per-word loop (`add`)
            compiled.prepare(scatter.append_kernel)

    @property
    def alive(self) -> np.ndarray:
        """(n_places,) bool: which ids hold a place."""
        return self._alive[: self.n_places]

    @property
    def capacity(self) -> int:
        return int(self._alive.size)

    def _posting_bytes(self) -> int:
        return 4 + (8 if self.weighted else 0)

    def _set_ids(self, q: int, buffer: np.ndarray | None) -> np.ndarray | None:
        """Make `buffer` (C-contiguous int32, or None) word q's posting buffer. Every change of
        a buffer goes through here, so `addresses` never returns a stale address."""
        self._ids[q] = buffer
        self._stale[q] = True
        self._cap[q] = 0 if buffer is None else buffer.size
        return buffer

    def addresses(self, words: np.ndarray) -> np.ndarray:
        """Data address (intp) of each given word's posting buffer, 0 for none."""
        stale = words[self._stale[words]]
        if stale.size:
            ids, addr = self._ids, self._addr
            for q in stale.tolist():
                b = ids[q]
                addr[q] = 0 if b is None else b.ctypes.data
            self._stale[stale] = False
        return self._addr[words]

    def add(self, words: np.ndarray, weights: np.ndarray | None = None) -> int:
        """Store a place from its sorted unique word ids (and one weight per word when
        weighted); returns its id."""
        pid = self._free.pop() if self._free else self.n_places
        if pid >= np.iinfo(np.int32).max:
            raise InputError("inverted index is full (2^31 places)")
        if pid >= self._alive.size:
            cap = max(64, 2 * self._alive.size)
            self._alive = np.concatenate([self._alive, np.zeros(cap - self._alive.size, bool)])
        self._alive[pid] = True
        stored = words.astype(self._word_dtype)
        if not self.weighted and compiled.active() == "compiled":
            # Words whose buffer has room take the posting in one compiled pass; the loop below
            # then only allocates and grows buffers (a small share of a place's words at steady
            # state: docs/results.md, "Memory").
            room = self._cap[words] > self._len[words]
            fast = words[room]
            scatter.append_kernel()(self.addresses(fast), self._len[fast], np.int32(pid))
            self._len[fast] += 1
            words = words[~room]
        ids_of, lens, size = self._ids, self._len, self._posting_bytes()
        values = weights.tolist() if self.weighted else None
        for i, q in enumerate(words.tolist()):
            b, n = ids_of[q], lens[q]
            if b is None:
                b = self._set_ids(q, np.empty(4, np.int32))
                if self.weighted:
                    self._wts[q] = np.empty(4, np.float64)
                self._buffer_bytes += 4 * size
            elif n == b.size:
                m = grown(n)
                nb = np.empty(m, np.int32)
                nb[:n] = b
                b = self._set_ids(q, nb)
                if self.weighted:
                    nw = np.empty(m, np.float64)
                    nw[:n] = self._wts[q][:n]
                    self._wts[q] = nw
                self._buffer_bytes += (m - n) * size
            b[n] = pid
            if self.weighted:
                self._wts[q][n] = values[i]
            lens[q] = n + 1
        self._buffer_bytes += stored.nbytes
        if pid == self.n_places:
            self._words.append(stored)
            self.n_places += 1
        else:
            self._words[pid] = stored
        self.n_alive += 1
        return pid

    def remove(self, pid: int) -> None:
        """Forget a place: in each of its words' buffers its posting takes the last one's slot.

        Order within a buffer carries no meaning (a place holds one posting per word, so every
        place's sum runs over the query's words in the same order whatever the order inside a
        buffer), so removal is a search and one move per word, not a compaction.
        """
        if not (0 <= pid < self.n_places) or not self._alive[pid]:
            raise InputError(f"place {pid} is not in the index")
        size, ids_of, wts_of, lens = self._posting_bytes(), self._ids, self._wts, self._len
        words = self._words[pid]
        last = lens[words].astype(np.int64) - 1  # each word holds exactly one posting of pid
        lens[words] = last
        for q, k in zip(words.tolist(), last.tolist()):
            b = ids_of[q]
            i = int((b[: k + 1] == pid).argmax())
            b[i] = b[k]
            if self.weighted:
                wts_of[q][i] = wts_of[q][k]
            if k == 0:
                self._buffer_bytes -= b.size * size
                self._set_ids(q, None)
                if self.weighted:
                    wts_of[q] = None
            elif k * 4 <= b.size and b.size > 8:
                # Shrink a buffer that lost most of its postings, keeping room to grow.
                m = max(4, 2 * k)
                self._buffer_bytes -= (b.size - m) * size
                self._set_ids(q, b[:m].copy())
                if self.weighted:
                    wts_of[q] = wts_of[q][:m].copy()
        self._buffer_bytes -= words.nbytes
        self._words[pid] = None
        self._alive[pid] = False
        self._free.append(pid)
        self.n_alive -= 1

    def place_words(self, pid: int) -> np.ndarray:
        """Sorted word ids of a stored place."""
        w = self._words[pid] if 0 <= pid < self.n_places else None
        if w is None:
            raise InputError(f"place {pid} was removed")
        return w

    def ids(self, q: int) -> np.ndarray:
        """Place ids of word q's postings (a view; empty when none)."""
        b = self._ids[q]
        return np.zeros(0, np.int32) if b is None else b[: self._len[q]]

    def rows(self, words: np.ndarray, lens: np.ndarray) -> list[np.ndarray]:
        """Place ids of each word's postings (views), given words that hold some and their
        posting counts: the numpy scatter's hot path, so one list comprehension and no per-word
        calls."""
        ids = self._ids
        return [ids[q][:k] for q, k in zip(words.tolist(), lens.tolist())]

    def scatter(self, defaults: np.ndarray, words: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """defaults (n_places,) float64 plus weights[i] (float64) for every posting of words[i]
        (int, each at most once), per place: the scorers' hot path (runtime/aefabmap_runtime/core/rank/scatter.py)."""
        lens = self._len[words]
        has = lens > 0
        words, weights, lens = words[has], weights[has], lens[has]
        if compiled.active() == "compiled":
            return scatter.scatter_buffers(defaults, self.addresses(words), weights, lens)
        return scatter.scatter_scores(defaults, self.rows(words, lens), weights, lens.astype(np.int64))

    def weights(self, q: int) -> np.ndarray:
        """Weights of word q's postings, in the order of `ids(q)` (weighted lists only)."""
        w = self._wts[q]
        return np.zeros(0) if w is None else w[: self._len[q]]

    def state(self) -> MapState:
        """Everything add/remove built: postings in their order and with their buffer capacities
        (memory accounting must come out the same), word lists, free-id order."""
        st = MapState()
        n = self.n_places
        st.scalars.update(n_places=n, capacity=self.capacity)
        st.arrays["alive"] = self._alive[:n].copy()
        st.arrays["words_ptr"], st.arrays["words"] = pack_ragged(self._words, self._word_dtype)
        st.arrays["post_cap"] = np.array([0 if b is None else b.size for b in self._ids], np.int64)
        lens = self._len.tolist()
        st.arrays["post_ptr"], st.arrays["postings"] = pack_ragged(
            [None if b is None else b[:k] for b, k in zip(self._ids, lens)], np.int64)
        if self.weighted:
            st.arrays["weights"] = pack_ragged([None if w is None else w[:k] for w, k in zip(self._wts, lens)],
                                               np.float64)[1]
        st.arrays["free"] = np.array(self._free, np.int64)
        return st

    def load_state(self, st: MapState, weight_range: tuple[float, float] = (0.0, np.inf)) -> None:
        """Replace the contents by a checked state (see `state`); weights must lie in weight_range."""
        v = self.vocabulary_size
        n = st.scalar("n_places", int, lo=0, hi=np.iinfo(np.int32).max)
        cap = st.scalar("capacity", int, lo=n, hi=max(64, 2 * n) + 1)
        alive = st.array("alive", "b", (n,))
        words = st.array("words", "iu", (None,), lo=0, hi=v)
        wptr = check_ptr(st, "words_ptr", n, words.size)
        post_cap = st.array("post_cap", "iu", (v,), lo=0)
        postings = st.array("postings", "iu", (None,), lo=0, hi=max(n, 1))
        pptr = check_ptr(st, "post_ptr", v, postings.size)
        free = st.array("free", "iu", (None,), lo=0, hi=max(n, 1))
        weights = None
        if self.weighted:
            weights = st.array("weights", "f", (postings.size,))
            if not np.all((weights >= weight_range[0]) & (weights <= weight_range[1])):
                raise StateError(f"map state: posting weights outside [{weight_range[0]}, {weight_range[1]}]")
        lens, rows = np.diff(pptr), np.diff(wptr)
        if np.any(rows[~alive] != 0):
            raise StateError("map state: a removed place still has words")
        if np.any(lens > post_cap) or np.any((post_cap == 0) != (lens == 0)) or np.any(post_cap > 8 * lens + 8):
            raise StateError("map state: posting capacities do not fit their lengths")
        if np.unique(free).size != free.size or set(free.tolist()) != set(np.flatnonzero(~alive).tolist()):
            raise StateError("map state: free ids are not exactly the removed places")
        # Each place's words strictly increasing, and the postings exactly the (word, place) pairs.
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
        self._ids = [None] * v
        self._addr = np.zeros(v, np.intp)
        self._stale = np.zeros(v, bool)
        self._cap = np.zeros(v, np.int32)
        self._wts = [None] * v if self.weighted else []
        self._len = lens.astype(np.int32)
        size = self._posting_bytes()
        for q in np.flatnonzero(post_cap).tolist():
            c, lo, hi = int(post_cap[q]), int(pptr[q]), int(pptr[q + 1])
            b = np.empty(c, np.int32)
            b[: hi - lo] = postings[lo:hi]
            self._set_ids(q, b)
            if self.weighted:
                w = np.empty(c, np.float64)
                w[: hi - lo] = weights[lo:hi]
                self._wts[q] = w
            self._buffer_bytes += c * size
        self._free = free.tolist()

    def nbytes(self) -> int:
        """Bytes of posting buffers, word lists, the alive flags and list slots (O(1))."""
        # 8 bytes per list slot of self._words, plus the fixed per-word length, address, stale-flag and
        # capacity arrays.
        return int(self._buffer_bytes + self._alive.nbytes + 8 * len(self._words) + self._len.nbytes
                   + self._addr.nbytes + self._stale.nbytes + self._cap.nbytes)


class PostingsView:
    """Base of an index whose places live in ``self.postings`` (a PostingLists): the id range,
    the live places and their words, as the scorers read them."""

    postings: PostingLists

    @property
    def n_places(self) -> int:
        """Size of the id range (removed ids included)."""
        return self.postings.n_places

    @property
    def n_alive(self) -> int:
        return self.postings.n_alive

    @property
    def alive(self) -> np.ndarray:
        """(n_places,) bool: which ids hold a place."""
        return self.postings.alive

    def place_words(self, pid: int) -> np.ndarray:
        return self.postings.place_words(pid)
