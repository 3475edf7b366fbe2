"""Evidence over consecutive frames: chains of links, their bound, the map state and hostile states."""

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError, StateError
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.core.decide.sequence import MAX_LINKS, Link, SequenceConfig, SequenceEvidence


def test_two_weak_frames_on_neighbouring_stored_frames_pass_together():
    chain = SequenceEvidence(SequenceConfig(frames=2, tolerance=3, max_log10_nfa=-7.0))
    assert chain.update([Link(4, 40, -3.5), Link(9, 90, -1.0)]) is None  # no history yet
    best = chain.update([Link(5, 42, -3.6), Link(7, 70, -3.9)])
    assert best is not None
    link, total = best
    assert link.place == 5 and total == pytest.approx(-7.1)  # 70 has no link within 3 frames before it


def test_no_chain_when_stored_frames_jump_or_a_link_is_not_significant():
    c = SequenceConfig(frames=2, tolerance=3)
    chain = SequenceEvidence(c)
    chain.update([Link(1, 10, -5.0)])
    assert chain.update([Link(2, 14, -5.0)]) is None  # 4 stored frames apart
    chain = SequenceEvidence(c)
    chain.update([Link(1, 10, 0.5)])  # no evidence: not a link
    assert chain.update([Link(2, 11, -6.9)]) is None
    chain = SequenceEvidence(c)
    chain.update([Link(1, 10, -3.0)])
    assert chain.update([Link(2, 11, -3.9)]) is None  # -6.9 is not below -7
    assert chain.update([]) is None


def test_a_chain_is_withheld_when_a_stored_frame_that_is_not_its_neighbour_has_like_evidence():
    # Stored frames 40 and 42 share the far scene: chains of -9.33 and -9.24 cannot tell them apart.
    c = SequenceConfig(frames=2, tolerance=3, max_log10_nfa=-7.0)  # the default margin: a factor of two
    chain = SequenceEvidence(c)
    chain.update([Link(4, 41, -5.4)])
    assert chain.update([Link(3, 40, -3.93), Link(5, 42, -3.84)]) is None
    # More than twice as unlikely by chance is far enough.
    chain = SequenceEvidence(c)
    chain.update([Link(4, 41, -5.4)])
    link, total = chain.update([Link(3, 40, -3.93), Link(5, 42, -3.6)])
    assert link.place == 3 and total == pytest.approx(-9.33)
    # A neighbouring stored frame is the same place: no rival.
    chain = SequenceEvidence(c)
    chain.update([Link(4, 41, -5.4)])
    assert chain.update([Link(3, 40, -3.93), Link(5, 41, -3.9)])[0].place == 3
    # Margin 0: the most significant chain is taken, however close its rivals.
    chain = SequenceEvidence(SequenceConfig(frames=2, tolerance=3, margin_log10_nfa=0.0))
    chain.update([Link(4, 41, -5.4)])
    assert chain.update([Link(3, 40, -3.93), Link(5, 42, -3.84)])[0].place == 3


def test_a_query_without_links_breaks_the_chain():
    chain = SequenceEvidence(SequenceConfig(frames=3, tolerance=2))
    chain.update([Link(1, 10, -3.0)])
    chain.update([])
    assert chain.update([Link(3, 12, -9.0)]) is None
    chain.update([Link(4, 13, -3.0)])
    assert chain.update([Link(5, 14, -3.0)])[1] == pytest.approx(-15.0)


def test_three_frame_chain_takes_the_best_path():
    chain = SequenceEvidence(SequenceConfig(frames=3, tolerance=1))
    chain.update([Link(1, 10, -1.0), Link(2, 30, -4.0)])
    chain.update([Link(3, 11, -1.0), Link(4, 31, -4.0)])
    link, total = chain.update([Link(5, 12, -2.0), Link(6, 32, -0.5)])
    assert (link.place, total) == (6, pytest.approx(-8.5))


def test_state_round_trip_continues_identically():
    c = SequenceConfig(frames=3, tolerance=2)
    rng = np.random.default_rng(0)
    queries = [[Link(int(p), int(p) + int(rng.integers(-1, 2)), float(-rng.uniform(0, 5))) for p in
                rng.integers(0, 40, rng.integers(0, 5))] for _ in range(60)]
    a, b = SequenceEvidence(c), SequenceEvidence(c)
    for i, q in enumerate(queries):
        if i == 30:
            b.load_state(MapState(a.state().arrays))
        ra = a.update(q)
        rb = b.update(q) if i >= 30 else None
        if i >= 30:
            assert ra == rb


@pytest.mark.parametrize("arrays", [
    {"counts": np.array([2]), "frames": np.array([1]), "nfa": np.array([-1.0])},  # counts disagree
    {"counts": np.array([1, 1, 1]), "frames": np.array([1, 2, 3]), "nfa": np.array([-1.0] * 3)},  # too many queries
    {"counts": np.array([1]), "frames": np.array([1]), "nfa": np.array([0.5])},  # not a link
    {"counts": np.array([1]), "frames": np.array([1]), "nfa": np.array([np.nan])},
    {"counts": np.array([MAX_LINKS + 1]), "frames": np.arange(MAX_LINKS + 1), "nfa": -np.ones(MAX_LINKS + 1)},
    {"counts": np.array([-1]), "frames": np.zeros(0, np.int64), "nfa": np.zeros(0)},
    {"counts": np.array([1]), "frames": np.array([1.5]), "nfa": np.array([-1.0])},
    {"counts": np.array([1]), "frames": np.array([1])},
])
def test_hostile_states_are_refused(arrays):
    chain = SequenceEvidence(SequenceConfig(frames=3))
    with pytest.raises(StateError):
        chain.load_state(MapState(arrays))


@pytest.mark.parametrize("kwargs", [dict(frames=1), dict(frames=-1), dict(frames=17), dict(tolerance=-1),
                                    dict(link_log10_nfa=0.5), dict(max_log10_nfa=1.0),
                                    dict(max_log10_nfa=float("nan")), dict(link_log10_nfa=-8.0),
                                    dict(margin_log10_nfa=-0.5), dict(margin_log10_nfa=float("inf"))])
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ConfigError):
        SequenceConfig(**kwargs)
