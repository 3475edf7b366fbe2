"""Exact FAB-MAP 2.0 inference over a Chow-Liu tree with an incremental inverted index.

Pure: no I/O. The model, term by term, with its reference vector: docs/fabmap2.md.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from aefabmap_runtime.errors import InputError, StateError
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.core.rank.postings import PostingLists, PostingsView
from aefabmap_runtime.core.kernels import compiled
from aefabmap_runtime.core.rank.scatter import buffers_kernel, scatter_packed, scatter_scores
from aefabmap_runtime.core.rank.tree import ChowLiuTree


@dataclass(frozen=True)
class WordDetectionModel:
    """FAB-MAP's detector model: how reliably a word is detected, P(z=1 | e=1) and P(z=1 | e=0)."""

    pzge: float = 0.39
    pzgne: float = 0.0

    def __post_init__(self) -> None:
        if not (0.0 < self.pzge <= 1.0) or not (0.0 <= self.pzgne < 1.0) or self.pzgne >= self.pzge:
            raise InputError(f"detector model needs 0 <= pzgne < pzge <= 1, got pzge={self.pzge}, pzgne={self.pzgne}")


def observation_term(tree: ChowLiuTree, det: WordDetectionModel, z: int, zp: int, l: int, naive_bayes: bool = False) -> np.ndarray:
    """G(z, zp, l) = P(z_q = z | z_pq = zp, place observation l) for every word, shape (V,).

    The detector and Chow-Liu terms combine as openFABMAP's PzqGL does (which is what the
    reference vector in docs/fabmap2.md was produced with).
    """
    p = tree.p
    pz_given_e = {1: det.pzge, 0: det.pzgne}  # P(z=1 | e)

    def pz(zz: int, e: int) -> float:
        return pz_given_e[e] if zz else 1.0 - pz_given_e[e]

    marg = {1: p, 0: 1.0 - p}
    cond1 = tree.p_given_parent if zp else tree.p_given_not_parent
    cond = {1: cond1, 0: 1.0 - cond1}
    # Posterior of word existence given the place's own observation l.
    num = {e: pz(l, e) * marg[e] for e in (0, 1)}
    pe = {e: num[e] / (num[0] + num[1]) for e in (0, 1)}
    g = np.zeros_like(p)
    for e in (0, 1):
        if naive_bayes:
            g = g + pe[e] * pz(z, e)
            continue
        alpha = marg[z] * pz(1 - z, e) * cond[1 - z]
        beta = marg[1 - z] * pz(z, e) * cond[z]
        g = g + pe[e] * beta / (alpha + beta)
    return g


@dataclass(frozen=True)
class FabMapTables:
    """Per-word log-likelihood increments d1..d4 (float64, shape (V,)) and the tree's children."""

    d1: np.ndarray
    d2: np.ndarray
    d3: np.ndarray
    d4: np.ndarray
    parent: np.ndarray
    child_ptr: np.ndarray  # (V+1,) CSR pointer into child_idx
    child_idx: np.ndarray  # children of word q are child_idx[child_ptr[q]:child_ptr[q+1]]

    @classmethod
    def build(cls, tree: ChowLiuTree, det: WordDetectionModel, naive_bayes: bool = False) -> "FabMapTables":
        def ratio(z: int, zp: int) -> np.ndarray:
            return np.log(observation_term(tree, det, z, zp, 1, naive_bayes) / observation_term(tree, det, z, zp, 0, naive_bayes))

        d1 = ratio(0, 0)
        d2 = ratio(0, 1) - d1
        d3 = ratio(1, 0) - d1
        d4 = ratio(1, 1) - d1
        if naive_bayes:
            # No tree: the parent's value plays no part.
            d2 = np.zeros_like(d1)
            d4 = d3.copy()
        v = tree.size
        kids = np.flatnonzero(tree.parent != np.arange(v))
        order = np.argsort(tree.parent[kids], kind="stable")
        child_idx = kids[order].astype(np.int64)
        child_ptr = np.zeros(v + 1, np.int64)
        np.add.at(child_ptr, tree.parent[kids] + 1, 1)
        child_ptr = np.cumsum(child_ptr)
        return cls(d1, d2, d3, d4, tree.parent, child_ptr, child_idx)

    def query_weights(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Words whose postings a query touches and the increment each posting gets.

        For each present word q: d4[q] if its parent is present else d3[q]; for each
        absent child c of a present word: d2[c]. Returns (word ids, weights).
        """
        v = self.d1.size
        present = np.zeros(v, bool)
        present[words] = True
        parent_present = present[self.parent[words]]
        w_present = np.where(parent_present, self.d4[words], self.d3[words])
        starts, ends = self.child_ptr[words], self.child_ptr[words + 1]
        counts = ends - starts
        if counts.sum():
            kids = self.child_idx[_ranges(starts, counts)]
            kids = kids[~present[kids]]
        else:
            kids = np.zeros(0, np.int64)
        touched = np.concatenate([words, kids])
        weights = np.concatenate([w_present, self.d2[kids]])
        nonzero = weights != 0.0
        return touched[nonzero], weights[nonzero]


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + c) for each (s, c), vectorised; int64."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offsets = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    return offsets + np.arange(total, dtype=np.int64)


def distinct_sorted(values: np.ndarray) -> np.ndarray:
    """The distinct values of a 1-D array, ascending (np.unique's result; a sort and one
    comparison cost less than np.unique at the hundreds of words of a frame)."""
    ordered = np.sort(values)
    if ordered.size < 2:
        return ordered
    first = np.empty(ordered.size, bool)
    first[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    return ordered[first]


def as_word_set(obs, vocabulary_size: int) -> np.ndarray:
    """Validate an observation (sequence of word ids) -> sorted unique int64 array."""
    arr = np.asarray(obs)
    if arr.size == 0:
        return np.zeros(0, np.int64)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"an observation must be a 1-D sequence of integer word ids, got {arr.dtype} {arr.shape}")
    arr = distinct_sorted(arr.astype(np.int64))
    if arr[0] < 0 or arr[-1] >= vocabulary_size:
        raise InputError(f"word ids must lie in [0, {vocabulary_size}), got range [{arr[0]}, {arr[-1]}]")
    return arr


def as_word_sets(observations, vocabulary_size: int) -> list[np.ndarray]:
    """`as_word_set` of each observation (the same arrays and errors), with one sort for all of
    them instead of one per observation (a bundle holds thousands)."""
    arrays = [np.asarray(obs) for obs in observations]
    for arr in arrays:
        if arr.size and (arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer)):
            raise InputError(f"an observation must be a 1-D sequence of integer word ids, got {arr.dtype} {arr.shape}")
    sizes = np.array([arr.size for arr in arrays], np.int64)
    if not sizes.sum():
        return [np.zeros(0, np.int64) for _ in arrays]
    flat = np.concatenate([arr.astype(np.int64, copy=False).ravel() for arr in arrays])
    if flat.min() < 0 or flat.max() >= vocabulary_size:
        raise InputError(f"word ids must lie in [0, {vocabulary_size}), got range [{flat.min()}, {flat.max()}]")
    # One key per (observation, word): sorted, each observation's words come out sorted and unique.
    keys = distinct_sorted(np.repeat(np.arange(len(arrays), dtype=np.int64), sizes) * vocabulary_size + flat)
    owner = keys // vocabulary_size
    words = keys - owner * vocabulary_size
    bounds = np.searchsorted(owner, np.arange(len(arrays) + 1))
    return [words[bounds[i]: bounds[i + 1]] for i in range(len(arrays))]


class InvertedIndex(PostingsView):
    """FAB-MAP's places: word -> place postings (runtime/aefabmap_runtime/core/rank/postings.py) plus each place's
    default score (the sum of d1 over its words, what a query that touches none of them scores).

    Cost of a query is proportional to the postings it touches, not to the number of places.
    A posting holds only its place id, as int32 (the per-word weight is the query's): 4 bytes.
    At 300 words a place costs ~300 * (4 * 1.1 + 2) bytes + 17 (alive, default, list slot).
    """

    def __init__(self, vocabulary_size: int) -> None:
        self.vocabulary_size = vocabulary_size
        self.postings = PostingLists(vocabulary_size)
        self._default = np.zeros(0, np.float64)

    def add(self, words: np.ndarray, default: float) -> int:
        """Append a place with sorted unique word ids and its default score; returns its id."""
        pid = self.postings.add(words)
        if self._default.size < self.postings.capacity:
            self._default = np.concatenate([self._default, np.zeros(self.postings.capacity - self._default.size)])
        self._default[pid] = default
        return pid

    def remove(self, pid: int) -> None:
        """Forget a place (PostingLists.remove) and its default score."""
        self.postings.remove(pid)
        self._default[pid] = 0.0

    def scores(self, touched: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """default + sum of weights over each place's touched postings, shape (n_places,)."""
        return self.postings.scatter(self._default[: self.n_places], touched, weights)

    def state(self) -> MapState:
        """The postings' state (defaults are recomputed from the words on load)."""
        return self.postings.state()

    def load_state(self, st: MapState, default) -> None:
        """Replace the contents by a checked state; default(words int64) -> a place's default score."""
        self.postings.load_state(st)
        self._default = np.zeros(self.postings.capacity, np.float64)
        for pid in np.flatnonzero(self.postings.alive).tolist():
            self._default[pid] = default(self.postings.place_words(pid).astype(np.int64))

    def nbytes(self) -> int:
        """Bytes held by posting buffers, per-place word lists and per-place arrays (O(1))."""
        return self.postings.nbytes() + int(self._default.nbytes)


class StaticPostings:
    """Word -> observation postings of a fixed set of observations, packed once (CSR, int32).

    Holds the new-place model's training observations: scored like the places, by the same
    scatter. The compiled scatter reads each word's postings in place (their offsets into the
    packed array, which made the query faster: CHANGELOG.md, "Per-frame cost on an AVX-512
    core"); the numpy one gathers them with one vectorised index, no per-word loop.
    """

    def __init__(self, observations: list[np.ndarray], defaults: np.ndarray, vocabulary_size: int) -> None:
        """observations: sorted unique int64 word ids each; defaults: (M,) float64 base scores."""
        self.n_places = len(observations)
        self.defaults = np.asarray(defaults, np.float64)
        rows = np.array([o.size for o in observations], np.int64)
        words = np.concatenate(observations) if observations else np.zeros(0, np.int64)
        owner = np.repeat(np.arange(self.n_places, dtype=np.int32), rows)
        # Stable sort by word keeps each word's postings in observation order (as 16-bit keys where
        # the ids fit: numpy sorts those by radix, in one pass).
        keys = words.astype(np.uint16) if vocabulary_size <= 1 << 16 else words
        order = np.argsort(keys, kind="stable")
        self.postings = owner[order]
        self.ptr = np.concatenate([[0], np.cumsum(np.bincount(words, minlength=vocabulary_size))]).astype(np.int64)

    def scores(self, touched: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """default + sum of weights over each observation's touched postings, shape (M,)."""
        starts = self.ptr[touched]
        lens = self.ptr[touched + 1] - starts
        if compiled.active() == "compiled":
            # Each word's postings read where they lie in the packed array: no gathered copy.
            return scatter_packed(self.defaults, self.postings, starts, weights, lens)
        rows = [self.postings[_ranges(starts, lens)]] if lens.size else []
        return scatter_scores(self.defaults, rows, weights, lens)

    def nbytes(self) -> int:
        return int(self.postings.nbytes + self.ptr.nbytes + self.defaults.nbytes)


@dataclass
class Localization:
    """Result of one FAB-MAP query.

    p_new: probability that the query is a new place.
    p_places: (n,) probabilities of the places stored before the query (0 for removed ones).
    loglik: (n,) log-likelihoods of those places; loglik_new: of the new place.
    place_id: id given to the query if it was added, else None.
    """

    p_new: float
    p_places: np.ndarray
    loglik: np.ndarray
    loglik_new: float
    place_id: int | None = None
    best_place: int | None = field(init=False)
    best_probability: float = field(init=False)

    def __post_init__(self) -> None:
        if self.p_places.size:
            self.best_place = int(np.argmax(self.p_places))
            self.best_probability = float(self.p_places[self.best_place])
        else:
            self.best_place = None
            self.best_probability = 0.0


class FabMap2:
    """FAB-MAP 2.0 with the sampled new-place model.

    tree: ChowLiuTree over V words.
    training_observations: sequence of observations (word-id sequences) for the new-place
        likelihood (logsumexp over them minus log M).
    pzge, pzgne: detector model. smoothing: s in P = s * softmax + (1 - s) / (n + 1).
    motion_model: use the previous posterior as prior (p_new_prior, bias) as in docs/fabmap2.md.
    naive_bayes: ignore the tree (independent words).
    """

    def __init__(
        self,
        tree: ChowLiuTree,
        training_observations,
        pzge: float = 0.39,
        pzgne: float = 0.0,
        smoothing: float = 0.99,
        *,
        naive_bayes: bool = False,
        motion_model: bool = False,
        p_new_prior: float = 0.9,
        motion_bias: float = 0.5,
    ) -> None:
        if not (0.0 < smoothing <= 1.0):
            raise InputError(f"smoothing must lie in (0, 1], got {smoothing}")
        self.tree = tree
        self.detection = WordDetectionModel(pzge, pzgne)
        self.smoothing = smoothing
        self.naive_bayes = naive_bayes
        self.motion_model = motion_model
        self.p_new_prior = p_new_prior
        self.motion_bias = motion_bias
        self.tables = FabMapTables.build(tree, self.detection, naive_bayes)
        self.vocabulary_size = tree.size
        self.places = InvertedIndex(tree.size)
        training = as_word_sets(training_observations, tree.size)
        defaults = np.array([float(self.tables.d1[w].sum()) for w in training], np.float64)
        self._training = StaticPostings(training, defaults, tree.size)
        if self._training.n_places == 0:
            raise InputError("FAB-MAP needs at least one training observation for the new-place model")
        compiled.prepare(buffers_kernel)
        self._prior: np.ndarray | None = None

    def empty_like(self) -> FabMap2:
        """A FabMap2 of the same model with no places and no prior; it shares this one's
        read-only tables and new-place model (other robots' places: runtime/aefabmap_runtime/core/fleet/fleet_map.py)."""
        other = copy.copy(self)
        other.places = InvertedIndex(self.vocabulary_size)
        other._prior = None
        return other

    @property
    def n_places(self) -> int:
        """Size of the place-id range (loglik and p_places have this length)."""
        return self.places.n_places

    def add(self, obs) -> int:
        """Store an observation as a new place; returns its id (0, 1, 2, ...)."""
        w = as_word_set(obs, self.vocabulary_size)
        return self.places.add(w, float(self.tables.d1[w].sum()))

    def remove(self, place_id: int) -> None:
        """Forget a place (bounded-memory policies); its id is reused by a later add()."""
        self.places.remove(place_id)

    def loglik(self, obs) -> np.ndarray:
        """log P(z | L) up to a per-query constant, for every stored place, shape (n_places,)."""
        touched, weights = self.tables.query_weights(as_word_set(obs, self.vocabulary_size))
        return self._masked(self.places.scores(touched, weights))

    def loglik_new(self, obs) -> float:
        """Sampled new-place log-likelihood: logsumexp over training observations - log M."""
        touched, weights = self.tables.query_weights(as_word_set(obs, self.vocabulary_size))
        return self._loglik_new(touched, weights)

    def _loglik_new(self, touched, weights) -> float:
        t = self._training.scores(touched, weights)
        return float(_logsumexp(t) - np.log(t.size))

    def _masked(self, scores: np.ndarray) -> np.ndarray:
        if self.places.n_alive < self.places.n_places:
            scores[~self.places.alive] = -np.inf
        return scores

    def localize(self, obs, add: bool = True) -> Localization:
        """Posterior over {new place, stored places}; optionally add the query as a place."""
        w = as_word_set(obs, self.vocabulary_size)
        touched, weights = self.tables.query_weights(w)
        l_places = self._masked(self.places.scores(touched, weights))
        l_new = self._loglik_new(touched, weights)
        m_new, m_places = l_new, l_places
        if self.motion_model:
            m_new, m_places = self._apply_motion_prior(l_new, l_places)
        probs = self._normalise(m_new, m_places)
        res = Localization(float(probs[0]), probs[1:], l_places, l_new)
        if self.motion_model:
            self._prior = probs
        if add:
            res.place_id = self.places.add(w, float(self.tables.d1[w].sum()))
        return res

    def _normalise(self, l_new: float, l_places: np.ndarray) -> np.ndarray:
        logs = np.concatenate([[l_new], l_places])
        # One exp pass (it is most of this function's cost at 100k places): softmax as
        # exp(x - max) / sum; a finite sum means no removed (-inf) place.
        if np.isfinite(logs.sum()):
            return self._smoothed(logs, logs.size)
        alive = np.isfinite(logs)
        probs = np.zeros_like(logs)
        probs[alive] = self._smoothed(logs[alive], int(alive.sum()))
        return probs

    def _smoothed(self, logs: np.ndarray, n_alive: int) -> np.ndarray:
        """s * softmax(logs) + (1 - s) / n_alive, for finite logs (a new array)."""
        p = logs - logs.max()
        np.exp(p, out=p)
        p *= self.smoothing / p.sum()
        p += (1.0 - self.smoothing) / n_alive
        return p

    def _apply_motion_prior(self, l_new: float, l_places: np.ndarray) -> tuple[float, np.ndarray]:
        prior = self._prior
        m_new = l_new + np.log(self.p_new_prior)
        if prior is None or prior.size < 2:
            return m_new, l_places
        pi = prior[1:]  # previous posterior over the places stored then
        k = pi.size
        b = self.motion_bias
        left = np.concatenate([[pi[0]], pi[:-1]])
        right = np.concatenate([pi[1:], [pi[-1]]])
        mix = (2 * (1 - b) * left + pi + 2 * b * right) / 3.0
        m = l_places.copy()
        with np.errstate(divide="ignore"):
            m[:k] = l_places[:k] + np.log(mix)
        return m_new, m

    def nbytes(self) -> int:
        """Memory held by the place index (postings, word lists, per-place arrays)."""
        return self.places.nbytes()

    def state(self) -> MapState:
        """The places (not the bundle's training index) and the motion model's last posterior."""
        st = MapState()
        st.put("places", self.places.state())
        st.scalars["has_prior"] = self._prior is not None
        if self._prior is not None:
            st.arrays["prior"] = self._prior.copy()
        return st

    def load_state(self, st: MapState) -> None:
        """Replace the places by a checked state (place defaults are recomputed from the words)."""
        d1 = self.tables.d1
        self.places.load_state(st.part("places"), lambda w: float(d1[w].sum()))
        self._prior = None
        if st.scalar("has_prior", bool):
            prior = st.array("prior", "f", (None,))
            if prior.size > self.places.n_places + 1:
                raise StateError("map state: motion prior is longer than the place range")
            self._prior = prior.astype(np.float64)


def _logsumexp(x: np.ndarray) -> float:
    m = float(np.max(x))
    return m + float(np.log(np.sum(np.exp(x - m))))
