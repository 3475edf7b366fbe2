"""The map apart from the detector (runtime/aefabmap_runtime/core/map/place_map.py): delayed insertion, the
caps' least-recently-used eviction, the events its listeners hear, and its state round trip."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import StateError
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.map.keypoint_store import KeypointStore
from aefabmap_runtime.core.map.map_events import MapListener
from aefabmap_runtime.core.map.place_map import Insertion, PlaceMap
from aefabmap_runtime.core.rank.bow import BowIndex
from aefabmap_runtime.core.rank.scorer import BowScorer

VOCABULARY = 50


class _Heard(MapListener):
    """Every map event, in order."""

    def __init__(self) -> None:
        self.events = []

    def place_inserted(self, place, frame, words, keypoints) -> None:
        self.events.append(("inserted", place, frame, keypoints is not None))

    def place_evicted(self, place) -> None:
        self.events.append(("evicted", place))

    def map_loaded(self) -> None:
        self.events.append(("loaded",))


def _words(frame: int) -> np.ndarray:
    """A few word ids of frame `frame` (repeats kept, as a frame's keypoints give them)."""
    return np.random.default_rng(frame).integers(0, VOCABULARY, 12).astype(np.int64)


def _keypoints(store: KeypointStore, frame: int, n: int = 8):
    rng = np.random.default_rng(100 + frame)
    xy = rng.random((n, 2)).astype(np.float32) * [640, 480]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return store.pack(xy, rng.integers(0, VOCABULARY, n), desc, (480, 640))


def _map(exclude: int = 2, verify: bool = True, **caps) -> PlaceMap:
    training = [np.unique(_words(1000 + i)) for i in range(20)]
    store = KeypointStore(get_kind("orb"), VOCABULARY) if verify else None
    return PlaceMap(BowScorer(BowIndex(VOCABULARY, training)), store, scorer_name="bow", vocabulary_size=VOCABULARY,
                    exclude=exclude, **caps)


def _feed(m: PlaceMap, frames: int) -> list[Insertion]:
    """`frames` frames through the map as the detector takes them: numbered, then queued."""
    done = []
    for _ in range(frames):
        seq, inserted = m.begin_frame()
        m.queue(seq, _words(seq), _keypoints(m.store, seq) if m.store is not None else None)
        done.append(inserted)
    return done


def test_a_frame_enters_the_map_exclude_frames_after_it_was_taken():
    m = _map(exclude=2)
    heard = _Heard()
    m.listeners.add(heard)
    done = _feed(m, 5)
    assert [d.frame for d in done] == [None, None, 0, 1, 2] and [d.place for d in done] == [None, None, 0, 1, 2]
    assert m.next_sequence == 5 and m.frames_inserted == 3 and m.n_places == 3
    assert [f for f, _, _ in m.queued()] == [3, 4]
    assert m.places() == [(0, 0), (1, 1), (2, 2)] and list(m.place_frames()) == [0, 1, 2]
    assert heard.events == [("inserted", p, p, True) for p in range(3)]
    assert m.holds(2) and not m.holds(3) and not m.holds(-1)
    assert m.keypoints(1) is not None and len(m.keypoints(1)) == 8


def test_the_cap_evicts_the_least_recently_used_place_and_tells_its_listeners():
    m = _map(exclude=1, max_places=3)
    heard = _Heard()
    m.listeners.add(heard)
    _feed(m, 4)  # frames 0-2 stored
    m.mark_used(0, 3)  # frame 3 closed a loop onto place 0: place 1 is now the least recently used
    done = _feed(m, 1)[0]
    assert done == Insertion(frame=3, place=1, evicted=1)  # the freed id is reused
    assert m.places() == [(0, 0), (1, 3), (2, 2)] and m.n_places == 3
    assert heard.events[-2:] == [("evicted", 1), ("inserted", 1, 3, True)]
    assert m.room() == (0, None)


def test_a_memory_cap_holds_and_every_eviction_is_heard():
    m = _map(exclude=0, memory_mb=0.04)  # less than 120 of these places take
    heard = _Heard()
    m.listeners.add(heard)
    _feed(m, 120)
    assert m.map_bytes() <= 0.04 * 2**20 and m.room() == (None, int(0.04 * 2**20) - m.map_bytes())
    evicted = [e[1] for e in heard.events if e[0] == "evicted"]
    inserted = [e[1] for e in heard.events if e[0] == "inserted"]
    assert evicted and len(inserted) - len(evicted) == m.n_places


def test_the_state_round_trip_rebuilds_the_map_and_checks_it():
    m = _map(exclude=2, max_places=4)
    _feed(m, 9)
    st = m.state().resolve()
    again = _map(exclude=2, max_places=4)
    heard = _Heard()
    again.listeners.add(heard)
    assert again.load_state(st, lambda seq: ("checked", seq)) == ("checked", 9)
    assert heard.events == [("loaded",)] and again.map_epoch == m.map_epoch
    assert again.places() == m.places() and again.next_sequence == 9 and again.map_bytes() == m.map_bytes()
    assert [(f, list(w)) for f, w, _ in again.queued()] == [(f, list(w)) for f, w, _ in m.queued()]
    # both go on alike
    assert _feed(again, 3) == _feed(m, 3) and again.places() == m.places()
    with pytest.raises(StateError, match="differ in geometric verification"):
        _map(verify=False).load_state(st)
    bad = m.state().resolve()
    bad.scalars["scorer"] = "fabmap"
    with pytest.raises(StateError, match="built with the 'fabmap' scorer, this run uses 'bow'"):
        _map().load_state(bad)


def test_a_tool_can_build_a_map_without_queries():
    m = _map(verify=False)
    for _ in range(3):
        frame, inserted = m.begin_frame()
        assert inserted == Insertion()  # nothing was queued
        assert m.add_place(np.unique(_words(frame)), frame) == (frame, None)
    assert m.next_sequence == 3 and m.n_places == 3 and m.keypoints(0) is None
    assert list(m.place_words(1)) == list(np.unique(_words(1)))


def test_a_read_only_map_takes_its_queued_frames_on_schedule_and_nothing_else():
    m = _map(exclude=2, max_places=3)
    _feed(m, 6)  # frames 0-3 stored within the cap (one evicted), frames 4 and 5 queued
    before = {p: (f, list(m.place_words(p))) for p, f in m.places()}
    used = m.state().arrays["last_used"]
    heard = _Heard()
    m.listeners.add(heard)
    m.read_only = True
    done = _feed(m, 50)  # frames 6-55: ranked against the map, never queued
    m.mark_used(0, 60)
    # The building run's frames 4 and 5 enter when its insertion delay has passed (frames 6 and
    # 7), over the cap rather than evicting what was stored; frames of this run never enter.
    assert [d.frame for d in done[:3]] == [4, 5, None] and all(d == Insertion() for d in done[2:])
    assert all(d.evicted is None for d in done) and [e[0] for e in heard.events] == ["inserted", "inserted"]
    assert m.next_sequence == 56 and m.n_places == 5 and m.queued() == []
    assert sorted(f for _, f in m.places()) == sorted([f for f, _ in before.values()] + [4, 5])
    assert all((f, list(m.place_words(p))) == before[p] for p, f in m.places() if p in before)
    assert all(m.state().arrays["last_used"][p] == used[p] for p in before)  # no use recorded
    with pytest.raises(StateError, match="read-only"):
        m.add_place(_words(70), 54)
