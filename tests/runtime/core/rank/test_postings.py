"""Posting lists shared by FAB-MAP's and BoW's indexes: add, remove, id reuse, state round trip,
memory accounting, hostile states."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import InputError, StateError
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.core.rank.postings import PostingLists

V = 50


def _places(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.unique(rng.integers(0, V, rng.integers(1, 30))) for _ in range(n)]


def _filled(weighted: bool) -> tuple[PostingLists, dict[int, np.ndarray]]:
    lists, held = PostingLists(V, weighted=weighted), {}
    for words in _places(120):
        held[lists.add(words, words / V if weighted else None)] = words
    for pid in (3, 7, 8, 60):
        lists.remove(pid)
        del held[pid]
    return lists, held


def _postings_by_word(lists: PostingLists) -> dict[int, list]:
    return {q: lists.ids(q).tolist() for q in range(V)}


@pytest.mark.parametrize("weighted", [False, True])
def test_postings_are_exactly_the_places_words_after_adds_and_removals(weighted, kernels):
    lists, held = _filled(weighted)
    for q in range(V):
        expected = sorted(pid for pid, words in held.items() if q in words)
        assert sorted(lists.ids(q).tolist()) == expected
        if weighted:
            assert np.allclose(lists.weights(q), q / V)
    assert lists.n_alive == len(held) and lists.alive.sum() == len(held)
    # Removed ids are reused, latest first, before the id range grows.
    assert lists.add(np.array([1, 2]), np.array([0.1, 0.2]) if weighted else None) == 60
    with pytest.raises(InputError):
        lists.remove(3)
    with pytest.raises(InputError):
        lists.place_words(7)


def test_compiled_append_builds_the_state_the_loop_builds(on_both_paths):
    """Adds take the compiled append where a buffer has room: postings, their order, buffer
    capacities and byte counts must be those of the per-word loop, through removals and reuse."""
    def build():
        lists = _churned(0)
        lists.add(np.arange(0, V, 3))
        return lists.state(), lists.nbytes()

    (a, bytes_a), (b, bytes_b) = on_both_paths(build)
    assert bytes_a == bytes_b and a.scalars == b.scalars and a.arrays.keys() == b.arrays.keys()
    for key in a.arrays:
        np.testing.assert_array_equal(a.arrays[key], b.arrays[key], err_msg=key)


@pytest.mark.parametrize("weighted", [False, True])
def test_state_round_trip_keeps_postings_order_capacities_and_bytes(weighted, kernels):
    lists, _ = _filled(weighted)
    st = lists.state()
    again = PostingLists(V, weighted=weighted)
    again.load_state(MapState(dict(st.arrays), dict(st.scalars)))
    assert _postings_by_word(again) == _postings_by_word(lists)
    assert again.nbytes() == lists.nbytes()
    assert again.n_places == lists.n_places and np.array_equal(again.alive, lists.alive)
    w = np.array([0.5]) if weighted else None
    assert again.add(np.array([4]), w) == lists.add(np.array([4]), w)  # the same free id next


def test_a_removed_word_buffer_shrinks_and_bytes_come_back():
    lists = PostingLists(V)
    empty = lists.nbytes()
    pids = [lists.add(np.array([0, 1])) for _ in range(200)]
    for pid in pids:
        lists.remove(pid)
    assert lists.ids(0).size == 0
    # Only the id range's bookkeeping (alive flags, list slots) remains.
    assert lists.nbytes() - empty == lists.capacity + 8 * 200


@pytest.mark.parametrize("name, value, message", [
    ("weights", lambda a: a * 0 + 2.0, "weights outside"),
    ("postings", lambda a: a[::-1].copy(), "do not match"),
    ("free", lambda a: a[:-1].copy(), "free ids"),
    ("post_cap", lambda a: a * 100 + 100, "capacities"),
])
def test_hostile_states_are_refused_in_one_line(name, value, message):
    lists, _ = _filled(True)
    st = lists.state()
    arrays = dict(st.arrays)
    arrays[name] = value(arrays[name])
    with pytest.raises(StateError, match=message):
        PostingLists(V, weighted=True).load_state(MapState(arrays, dict(st.scalars)), weight_range=(0.0, 1.0))


def _reference_scatter(defaults: np.ndarray, lists: PostingLists, words: np.ndarray, weights: np.ndarray) -> np.ndarray:
    acc = defaults.copy()
    for q, w in zip(words.tolist(), weights.tolist()):
        acc[lists.ids(q).astype(np.intp)] += w
    return acc


def _churned(seed: int) -> PostingLists:
    """Adds and removals that grow, shrink and free word buffers, then a state round trip."""
    rng = np.random.default_rng(seed)
    lists = PostingLists(V)
    for step in range(400):
        alive = np.flatnonzero(lists.alive)
        if alive.size > 20 and rng.random() < 0.45:
            lists.remove(int(rng.choice(alive)))
        else:
            lists.add(np.unique(rng.integers(0, V, rng.integers(1, 25))))
        if step == 250:
            st = lists.state()
            lists = PostingLists(V)
            lists.load_state(MapState(dict(st.arrays), dict(st.scalars)))
    for pid in np.flatnonzero(lists.alive)[3:].tolist():  # most words' buffers shrink or go
        lists.remove(pid)
    return lists


def test_scatter_reads_every_buffer_where_it_lies_after_growth_shrinking_and_reload(kernels):
    """The compiled scatter reads postings through the buffers' data addresses: after any
    history of adds, removals (buffers shrunk or freed) and a state reload, it must read exactly
    the live buffers, as the numpy path and a per-word loop do."""
    for seed in range(3):
        lists = _churned(seed)
        every = lists.addresses(np.arange(V))
        for q in range(V):
            b = lists._ids[q]
            assert every[q] == (0 if b is None else b.ctypes.data)
        rng = np.random.default_rng(seed + 10)
        defaults = rng.standard_normal(lists.n_places)
        words = np.unique(rng.integers(0, V, 30))  # some hold no postings at all
        weights = rng.standard_normal(words.size)
        got = lists.scatter(defaults, words, weights)
        np.testing.assert_array_equal(got, _reference_scatter(defaults, lists, words, weights))
        assert got is not defaults
