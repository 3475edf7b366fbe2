"""One robot's map of places, kept apart from the model that describes them (pure).

As DBoW2 keeps its vocabulary and its database apart, the detector (core/detector.py) holds
the bundle (features, words, FAB-MAP's model) and ranks, verifies and decides, while
`PlaceMap` holds what the frames built: the place index (a Scorer, core/rank/scorer.py), the
keypoints each place keeps for verification (KeypointStore; None without verification), the
place id -> frame and last-used tables, the delayed-insertion queue, the frame counter and the
map epoch. It keeps the caps (max_places, memory_mb) by evicting the least recently used place,
accounts the map's memory (`map_bytes`), and saves / loads all of it as a MapState
(core/records/map_state.py). Its listeners (core/map/map_events.py) hear every insertion,
eviction and load.

A map can be made read-only (`read_only`, localization against a map built once): frames are
still numbered, ranked and verified against it, but none is queued, no place is evicted and no
use is recorded. The frames its building run still had queued enter on their schedule, as they
would have in that run: the insertion delay keeps the frames just after the map's own from
matching them, and the map ends with every frame that built it (its memory grows by that queue,
already held, and no more however long it runs).
"""

from __future__ import annotations

import secrets
from collections import deque
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import numpy as np

from aefabmap_runtime.errors import StateError
from aefabmap_runtime.core.map.keypoint_store import KeypointStore, PlaceKeypoints
from aefabmap_runtime.core.map.map_events import MapListeners
from aefabmap_runtime.core.rank.scorer import Scorer
from aefabmap_runtime.core.records.map_state import MapState, check_ptr, pack_ragged

T = TypeVar("T")
_NEVER = np.iinfo(np.int64).max


class Insertion(NamedTuple):
    """What one frame's step did to the map: the last frame inserted, its place id, and the last
    place id evicted to make room for it (None: none)."""

    frame: int | None = None
    place: int | None = None
    evicted: int | None = None


class PlaceMap:
    """The places of one map; see the module doc.

    scorer: an empty place index; store: an empty KeypointStore, or None (no verification).
    scorer_name: which index it is ("fabmap" or "bow"), checked against a loaded state.
    vocabulary_size: the bundle's, in words. exclude: frames a frame waits in the queue before it
    enters the map. max_places (places) / memory_mb (MiB, as `map_bytes` accounts): hard caps,
    None for unbounded; when one is reached the least recently used place is evicted first.
    """

    def __init__(self, scorer: Scorer, store: KeypointStore | None, *, scorer_name: str, vocabulary_size: int,
                 exclude: int, max_places: int | None = None, memory_mb: float | None = None) -> None:
        self.scorer, self.store = scorer, store
        self.scorer_name, self.vocabulary_size = scorer_name, int(vocabulary_size)
        self.exclude, self.max_places, self.memory_mb = exclude, max_places, memory_mb
        self.listeners = MapListeners()
        # (frame, observed words, keypoints) of the frames waiting to enter the map, oldest first.
        self._pending: deque[tuple[int, np.ndarray, PlaceKeypoints | None]] = deque()
        # place id -> frame that made it / last frame it was inserted or matched as a loop (-1: none).
        self._place_frame = np.zeros(0, np.int64)
        self._last_used = np.zeros(0, np.int64)
        self._sequence = 0
        # Names this map's frame numbering (a fleet tells other robots by it that a restarted
        # node's frame numbers mean other places): drawn for an empty map, kept in its state.
        self.map_epoch = secrets.randbits(64)
        #: Localization: no frame of this run enters the map, no place leaves it (see the module doc).
        self.read_only = False

    # -- what the map holds ------------------------------------------------------------------

    @property
    def n_places(self) -> int:
        """Places in the map now."""
        return self.scorer.n_alive

    @property
    def next_sequence(self) -> int:
        """Sequence number the next frame gets (frames continue across a saved state)."""
        return self._sequence

    @property
    def frames_inserted(self) -> int:
        """Frames that have entered the map since it was started (evicted ones included)."""
        return self._sequence - len(self._pending)

    def place_frames(self) -> np.ndarray:
        """(n,) int64 frame of each place id, n = the scorer's id range (removed ids included)."""
        return self._place_frame[: self.scorer.n_places]

    def holds(self, place: int) -> bool:
        """True when place id `place` holds a place now."""
        return 0 <= place < self.scorer.n_places and bool(self.scorer.alive[place])

    def places(self) -> list[tuple[int, int]]:
        """(place id, frame) of every place in the map, by id."""
        frames = self.place_frames()
        return [(int(p), int(frames[p])) for p in np.flatnonzero(self.scorer.alive[: frames.size])]

    def place_words(self, place: int) -> np.ndarray:
        """The sorted word ids place `place` was stored with."""
        return self.scorer.place_words(place)

    def keypoints(self, place: int) -> PlaceKeypoints | None:
        """The keypoints place `place` keeps for verification (None: none, or no verification)."""
        return self.store.get(place) if self.store is not None else None

    def queued(self) -> list[tuple[int, np.ndarray, PlaceKeypoints | None]]:
        """(frame, observed words, keypoints) of the frames waiting to enter the map, oldest first."""
        return list(self._pending)

    def map_bytes(self) -> int:
        """Memory of the map (index postings, word lists, per-place arrays), in bytes.

        The one place where per-place memory is accounted: whatever else is kept per place
        (e.g. keypoints for verification) must be added here so that memory_mb holds.
        """
        kps = self.store.nbytes() if self.store is not None else 0
        return self.scorer.nbytes() + self._last_used.nbytes + self._place_frame.nbytes + kps

    def room(self) -> tuple[int | None, int | None]:
        """(places, bytes) the caps leave beside the map now (None: no such cap); other robots'
        places live in it (core/fleet/fleet_map.py)."""
        places = None if self.max_places is None else self.max_places - self.n_places
        nbytes = None if self.memory_mb is None else int(self.memory_mb * 2**20) - self.map_bytes()
        return places, nbytes

    # -- a frame -----------------------------------------------------------------------------

    def begin_frame(self) -> tuple[int, Insertion]:
        """Number the next frame and move the queued frames whose delay has passed into the map;
        returns (the frame's sequence number, what entered and left)."""
        seq = self._sequence
        self._sequence += 1
        done = Insertion()
        while self._pending and self._pending[0][0] <= seq - self.exclude:
            frame, words, keypoints = self._pending.popleft()
            done = Insertion(frame, *self._store_place(words, frame, keypoints))
        return seq, done

    def queue(self, frame: int, words: np.ndarray, keypoints: PlaceKeypoints | None) -> None:
        """Queue frame `frame` (its observed words, its packed keypoints or None) for insertion
        `exclude` frames later (a read-only map queues nothing)."""
        if not self.read_only:
            self._pending.append((frame, words, keypoints))

    def mark_used(self, place: int, frame: int) -> None:
        """Place `place` was matched as a loop by frame `frame`: it is the last to be evicted now
        (a read-only map records nothing)."""
        if not self.read_only:
            self._last_used[place] = frame

    def add_place(self, words: np.ndarray, frame: int, keypoints: PlaceKeypoints | None = None
                  ) -> tuple[int, int | None]:
        """Store frame `frame` as a place now (words: its observed word ids; keypoints: kept when
        the map verifies), evicting to stay within the caps; returns (its place id, the last
        place id evicted or None). The queue's path, and a tool's that builds a map without
        queries (the frame must be below `next_sequence`). StateError on a read-only map."""
        if self.read_only:
            raise StateError("the map is read-only (localization): no place can be added")
        return self._store_place(words, frame, keypoints)

    def _store_place(self, words: np.ndarray, frame: int, keypoints: PlaceKeypoints | None
                     ) -> tuple[int, int | None]:
        """add_place's work, and the queue's in a read-only map, which evicts nothing."""
        evicted = None if self.read_only else self._make_room()
        place = int(self.scorer.add(words))
        if place >= self._last_used.size:
            grow = max(64, self._last_used.size)
            self._last_used = np.concatenate([self._last_used, np.full(grow, -1, np.int64)])
            self._place_frame = np.concatenate([self._place_frame, np.full(grow, -1, np.int64)])
        self._last_used[place] = frame
        self._place_frame[place] = frame
        if self.store is not None:
            # A reused id must not keep the keypoints of the place it belonged to before.
            self.store.remove(place)
            if keypoints is not None:
                self.store.put(place, keypoints)
        self.listeners.place_inserted(place, frame, words, self.keypoints(place))
        trimmed = None if self.read_only else self._trim(place)
        return place, trimmed if trimmed is not None else evicted

    # -- caps --------------------------------------------------------------------------------

    def _over_budget(self, extra_places: int = 1) -> bool:
        if self.max_places is not None and self.n_places + extra_places > self.max_places:
            return True
        if self.memory_mb is not None and self.n_places > 0:
            # Leave room for one more place of the average size before inserting it.
            per_place = self.map_bytes() / self.n_places
            return self.map_bytes() + per_place > self.memory_mb * 2**20
        return False

    def _make_room(self) -> int | None:
        """Evict least-recently-used places until one more fits; returns the last evicted id."""
        evicted = None
        while self.n_places > 0 and self._over_budget():
            evicted = self._evict_lru()
        return evicted

    def _trim(self, keep: int) -> int | None:
        """Evict least-recently-used places other than `keep` while the map exceeds memory_mb;
        returns the last evicted id. `_make_room` leaves room for a place of the average size,
        but an insertion can take more at once (a full posting buffer grows by a quarter), and
        the cap is a bound, not an average."""
        evicted = None
        while self.memory_mb is not None and self.n_places > 1 and self.map_bytes() > self.memory_mb * 2**20:
            evicted = self._evict_lru(keep)
        return evicted

    def _evict_lru(self, keep: int | None = None) -> int:
        alive = self.scorer.alive
        used = np.where(alive, self._last_used[: alive.size], _NEVER)
        if keep is not None:
            used[keep] = _NEVER
        evicted = int(np.argmin(used))
        self.scorer.remove(evicted)
        if self.store is not None:
            self.store.remove(evicted)
        self.listeners.place_evicted(evicted)
        return evicted

    # -- state -------------------------------------------------------------------------------

    def state(self) -> MapState:
        """The map as arrays + scalars (core/records/map_state.py): scorer postings, keypoint
        store, place -> frame table, last-used order, insertion queue, frame counter, epoch.
        The keypoints are packed by ``MapState.resolve()`` (e.g. in the thread that writes them)."""
        st = MapState()
        st.scalars.update(
            scorer=self.scorer_name, verification=self.store is not None, vocabulary_size=self.vocabulary_size,
            max_keypoints=self.store.max_keypoints if self.store is not None else None, sequence=self._sequence,
            n_places=self.scorer.n_places, n_alive=self.n_places, map_epoch=self.map_epoch,
        )
        st.put("scorer", self.scorer.state())
        st.arrays["place_frame"] = self._place_frame.copy()
        st.arrays["last_used"] = self._last_used.copy()
        pend = list(self._pending)
        st.arrays["pending_seq"] = np.array([p[0] for p in pend], np.int64)
        st.arrays["pending_words_ptr"], st.arrays["pending_words"] = pack_ragged([p[1] for p in pend], np.int64)
        if self.store is not None:
            st.put("store", self.store.state())
            store, pending_kps = self.store, [p[2] for p in pend]
            st.put("pending_kps", MapState(deferred=[("", lambda: store.pack_places(pending_kps))]))
        return st

    def load_state(self, st: MapState, check: Callable[[int], T] | None = None) -> T | None:
        """Replace the map by a checked state (see state()); raises StateError on any mismatch
        with this map's index, verification or vocabulary, or an array out of shape or bounds.
        check: the owner's checks of its own scalars, called with the state's frame counter
        once the map's scalars have passed and before anything is replaced; its result is
        returned (None without one)."""
        seq = self._check_scalars(st)
        checked = check(seq) if check is not None else None
        self.scorer.load_state(st.part("scorer"))
        n = self.scorer.n_places
        if st.scalar("n_places", int) != n or st.scalar("n_alive", int) != self.scorer.n_alive:
            raise StateError("map state: place counts disagree with the place index")
        place_frame = st.array("place_frame", "iu", (None,), lo=-1, hi=max(seq, 1))
        last_used = st.array("last_used", "iu", (place_frame.size,), lo=-1, hi=max(seq, 1))
        if place_frame.size < n or place_frame.size > max(64, 2 * n):
            raise StateError(f"map state: place tables hold {place_frame.size} ids for {n} places")
        if np.any(place_frame[:n][self.scorer.alive] < 0):
            raise StateError("map state: a stored place has no frame")
        pending = self._load_pending(st, seq, n)
        self._place_frame, self._last_used, self._pending, self._sequence = place_frame, last_used, pending, seq
        # A map saved before epochs were kept gets a new one (its fleet peers forget it once).
        if "map_epoch" in st.scalars:
            self.map_epoch = st.scalar("map_epoch", int, lo=0, hi=2**64)
        else:
            self.map_epoch = secrets.randbits(64)
        self.listeners.map_loaded()
        return checked

    def _check_scalars(self, st: MapState) -> int:
        """The state's index kind, verification, vocabulary and budget checked against this
        map's; returns its frame counter."""
        if (scorer := st.scalar("scorer", str)) != self.scorer_name:
            raise StateError(f"map state was built with the {scorer!r} scorer, this run uses {self.scorer_name!r}")
        if st.scalar("verification", bool) != (self.store is not None):
            raise StateError("map state and this run differ in geometric verification (on/off)")
        v = self.vocabulary_size
        if st.scalar("vocabulary_size", int) != v:
            raise StateError(f"map state has a vocabulary of {st.scalars['vocabulary_size']} words, the bundle {v}")
        if self.store is not None:
            # A map kept with another verification budget loads when every stored place fits this
            # run's cap (the keypoint store checks the counts): places keep the keypoints they have.
            st.scalar("max_keypoints", (int, type(None)))
        return st.scalar("sequence", int, lo=0, hi=2**62)

    def _load_pending(self, st: MapState, seq: int, n: int) -> deque:
        """The insertion queue of a state (the keypoint store is loaded on the way)."""
        pseq = st.array("pending_seq", "iu", (None,), lo=0, hi=max(seq, 1))
        if pseq.size > 1 and np.any(np.diff(pseq) <= 0):
            raise StateError("map state: the insertion queue is not in frame order")
        pwords = st.array("pending_words", "iu", (None,), lo=0, hi=self.vocabulary_size)
        pptr = check_ptr(st, "pending_words_ptr", pseq.size, pwords.size)
        pkps: list = [None] * pseq.size
        if self.store is not None:
            self.store.load_state(st.part("store"), n)
            if any(not self.scorer.alive[p] for p in self.store.place_ids()):
                raise StateError("map state: the keypoint store holds a removed place")
            pkps = self.store.unpack_places(st.part("pending_kps"), pseq.size)
        return deque((int(s), pwords[pptr[i]:pptr[i + 1]], pkps[i]) for i, s in enumerate(pseq.tolist()))
