"""Place scorers behind one interface: FAB-MAP 2.0 and tf-idf BoW (pure).

What the detector needs of a scorer: add a place, remove one (the map's caps evict places),
rank a query against every place (candidate order for verification and the fields of its
result), and the memory its index holds. Place ids are dense and reused after removal;
arrays over places have the length of the id range (`n_places`), removed ids included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.rank.bow import BowIndex
from aefabmap_runtime.core.rank.fabmap import FabMap2
from aefabmap_runtime.core.records.map_state import MapState

FABMAP_SCORES = ("probability", "llr")


@dataclass
class Ranking:
    """One query ranked against every place id (arrays of length n = the scorer's n_places).

    order: (n,) float64, larger ranks first; -inf for removed ids (FAB-MAP: log-likelihood,
        BoW: cosine similarity).
    scores: (n,) what the detector reports as the last scores: FAB-MAP's posterior, BoW's
        similarity; 0 for removed ids.
    best: id of the best place (None when the map is empty); score: the detector's score of it
        (0.0 when there is none).
    probability, llr, p_new: FAB-MAP's posterior of `best`, its log-likelihood ratio against
        the new place (nats) and the new-place probability; None for BoW.
    loglik_new: FAB-MAP's log-likelihood of the new place (order[i] - loglik_new is place i's
        LLR); None for BoW.
    """

    order: np.ndarray
    scores: np.ndarray
    best: int | None
    score: float
    probability: float | None = None
    llr: float | None = None
    p_new: float | None = None
    loglik_new: float | None = None


class Scorer(Protocol):
    """A place index the detector scores queries with (words: (N,) word ids, repeats allowed)."""

    @property
    def n_places(self) -> int:
        """Size of the place-id range (removed ids included)."""
        ...

    @property
    def n_alive(self) -> int:
        """Places currently stored."""
        ...

    @property
    def alive(self) -> np.ndarray:
        """(n_places,) bool: which ids hold a place."""
        ...

    def add(self, words: np.ndarray) -> int:
        """Store a place; returns its id (a removed id is reused first)."""
        ...

    def remove(self, place_id: int) -> None:
        """Forget a stored place."""
        ...

    def place_words(self, place_id: int) -> np.ndarray:
        """The sorted word ids a place was stored with."""
        ...

    def rank(self, words: np.ndarray) -> Ranking:
        """Rank a query against every stored place (the query is not added)."""
        ...

    def nbytes(self) -> int:
        """Bytes held per place by the index (what the detector's memory cap accounts)."""
        ...

    def state(self) -> MapState:
        """The stored places as arrays (runtime/aefabmap_runtime/core/records/map_state.py)."""
        ...

    def load_state(self, state: MapState) -> None:
        """Replace the stored places by a checked state; raises StateError."""
        ...


class FabMapScorer:
    """FAB-MAP 2.0 (FabMap2) as a Scorer.

    score: what Ranking.score holds: "probability" (normalised posterior of the best place)
    or "llr" (its log-likelihood ratio against the new-place model, nats).
    """

    def __init__(self, fabmap: FabMap2, score: str = "probability") -> None:
        if score not in FABMAP_SCORES:
            raise ConfigError(f"fabmap_score must be one of {FABMAP_SCORES}, got {score!r}")
        self.fabmap = fabmap
        self.score = score

    @property
    def n_places(self) -> int:
        return self.fabmap.n_places

    @property
    def n_alive(self) -> int:
        return self.fabmap.places.n_alive

    @property
    def alive(self) -> np.ndarray:
        return self.fabmap.places.alive

    def add(self, words: np.ndarray) -> int:
        return self.fabmap.add(words)

    def remove(self, place_id: int) -> None:
        self.fabmap.remove(place_id)

    def place_words(self, place_id: int) -> np.ndarray:
        """The sorted word ids a place was stored with."""
        return self.fabmap.places.place_words(place_id)

    def rank(self, words: np.ndarray) -> Ranking:
        loc = self.fabmap.localize(words, add=False)
        best = loc.best_place
        if best is None:
            return Ranking(loc.loglik, loc.p_places, None, 0.0, p_new=loc.p_new, loglik_new=float(loc.loglik_new))
        llr = float(loc.loglik[best] - loc.loglik_new)
        score = llr if self.score == "llr" else loc.best_probability
        return Ranking(loc.loglik, loc.p_places, best, score, loc.best_probability, llr, loc.p_new,
                       float(loc.loglik_new))

    def nbytes(self) -> int:
        return self.fabmap.nbytes()

    def state(self) -> MapState:
        return self.fabmap.state()

    def load_state(self, state: MapState) -> None:
        self.fabmap.load_state(state)


class BowScorer:
    """tf-idf cosine bag of words (BowIndex) as a Scorer; Ranking.score is the cosine similarity."""

    def __init__(self, index: BowIndex) -> None:
        self.index = index

    @property
    def n_places(self) -> int:
        return self.index.n_places

    @property
    def n_alive(self) -> int:
        return self.index.n_alive

    @property
    def alive(self) -> np.ndarray:
        return self.index.alive

    def add(self, words: np.ndarray) -> int:
        return self.index.add(words)

    def remove(self, place_id: int) -> None:
        self.index.remove(place_id)

    def place_words(self, place_id: int) -> np.ndarray:
        """The sorted word ids a place was stored with."""
        return self.index.postings.place_words(place_id)

    def rank(self, words: np.ndarray) -> Ranking:
        sims = self.index.similarity(words)
        order = sims
        if self.index.n_alive < sims.size:
            order = np.where(self.index.alive, sims, -np.inf)
        if self.index.n_alive == 0:
            return Ranking(order, sims, None, 0.0)
        best = int(np.argmax(order))
        return Ranking(order, sims, best, float(sims[best]))

    def nbytes(self) -> int:
        return self.index.nbytes()

    def state(self) -> MapState:
        return self.index.state()

    def load_state(self, state: MapState) -> None:
        self.index.load_state(state)
