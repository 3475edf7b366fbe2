"""The candidate policy on its own: which places it checks, in what order, within its caps
(the pair verdicts are scripted; the detector's tests cover the real verification)."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.decide.candidates import Attempt, CandidateConfig, CandidatePolicy, Search, tied_rival, top_places
from aefabmap_runtime.core.verify.verification import GeometryResult


class Script:
    """A PairCheck that passes the places in `passes` and records every call."""

    def __init__(self, passes=(), empty=()):
        self.passes, self.empty, self.calls, self.upright = set(passes), set(empty), [], []

    def __call__(self, pid, bruteforce, retry_only, upright=False):
        self.calls.append((pid, bruteforce, retry_only))
        self.upright.append(upright)
        if pid in self.empty:
            return None
        ok = pid in self.passes
        return GeometryResult(verified=ok, model="F", inliers=40 if ok else 3, nfa=-10.0 if ok else 2.0,
                              reason="" if ok else "chance")


def _moving_forwards(policy, seq, frame):
    """Queries seq - 1 and seq verified to stored frames frame - 1 and frame: a track running forwards."""
    c = policy.config
    policy.track.confirm(seq - 1, frame - 1, c.track_memory, c.track_reach)
    policy.track.confirm(seq, frame, c.track_memory, c.track_reach)


def _search(policy, seq, ranking, script, frames=None):
    frames = np.arange(ranking.size) if frames is None else frames
    top = top_places(ranking, policy.config.top_k)
    return policy.search(seq, top, ranking, frames, lambda p: True, script)


def test_fabmap_candidates_in_rank_order_first_pass_wins():
    ranking = np.array([0.1, 0.9, 0.5, 0.7, -np.inf])
    script = Script(passes={2})
    s = _search(CandidatePolicy(CandidateConfig(top_k=5, bruteforce_fallback=1)), 100, ranking, script)
    assert [c[0] for c in script.calls] == [1, 3, 2]  # best first, stops at the first that passes
    assert [c[1] for c in script.calls] == [True, False, False]  # only the best gets the brute-force retry
    assert s.verified and s.best_place == 2 and s.source == "fabmap" and s.tried == 3 and s.bruteforce == 1


def test_removed_places_are_never_checked_and_caps_hold():
    ranking = np.array([0.3, 0.2, 0.1, -np.inf])
    script = Script()
    s = _search(CandidatePolicy(CandidateConfig(top_k=4, max_trials=2, max_bruteforce=0)), 50, ranking, script)
    assert [c[0] for c in script.calls] == [0, 1] and s.tried == 2 and s.bruteforce == 0 and not s.verified


def test_track_window_comes_first_then_the_reach():
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=3, track_reach=3))
    _moving_forwards(policy, seq=10, frame=4)  # query 10 matched stored frame 4, 9 matched 3
    ranking = np.linspace(0, 1, 20)[::-1].copy()  # place 0 ranks best
    script = Script(passes={9})
    s = _search(policy, 11, ranking, script)
    # window: frames 5, 6 then 4; FAB-MAP's best (place 0); the reach around 5: 7 and 8, 2... nearest
    # first, ahead before behind, each with the retry; place 9 lies outside the reach: never found.
    order = [c[0] for c in script.calls]
    assert order[:4] == [5, 6, 4, 0]
    assert set(order[4:]) == {7, 8, 3, 2} and order[4] == 7 and not s.verified
    assert all(bf for pid, bf, _ in script.calls if pid != 0)
    # Upright descriptors for the tracked places (window and reach) only, never for FAB-MAP's.
    assert [up for (pid, _, _), up in zip(script.calls, script.upright)] == [pid != 0 for pid in order]


def test_a_same_word_check_gets_only_the_retry_when_the_reach_comes_to_it():
    policy = CandidatePolicy(CandidateConfig(top_k=3, bruteforce_fallback=0, track=1, track_reach=2))
    _moving_forwards(policy, seq=10, frame=5)
    ranking = np.zeros(12)
    ranking[7] = 1.0  # FAB-MAP's best is place 7: same-word matching only (no fallback)
    script = Script()
    s = _search(policy, 11, ranking, script)
    assert (7, False, False) in script.calls and (7, True, True) in script.calls
    assert s.tried == len({c[0] for c in script.calls})  # a retried place counts once


def test_track_lapses_after_its_memory_and_places_without_keypoints_are_skipped():
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=1, track_reach=0))
    _moving_forwards(policy, seq=10, frame=4)
    script = Script(empty={0})
    s = _search(policy, 12, np.linspace(1, 0, 8), script)  # lag 2 > memory 1: no track
    assert [c[0] for c in script.calls] == [0] and s.tried == 0 and s.best is None


def test_the_track_lasts_twice_its_reach_by_default():
    """The default memory: a revisit slower or faster than the first pass by up to half still has
    its true frame within the reach of the expected one when the memory ends."""
    config = CandidateConfig()
    assert config.track_memory == 2 * config.track_reach
    for lag, tracked in ((config.track_memory, True), (config.track_memory + 1, False)):
        policy = CandidatePolicy(CandidateConfig(top_k=1))
        _moving_forwards(policy, seq=10, frame=4)
        script = Script()
        _search(policy, 10 + lag, np.linspace(1, 0, 40), script)  # FAB-MAP's best: place 0
        assert (4 + lag in {c[0] for c in script.calls}) is tracked


class Graded(Script):
    """A Script whose passing places have their own log10 NFA (`nfa`: place -> value)."""

    def __init__(self, nfa):
        super().__init__(passes=set(nfa))
        self.nfa = nfa

    def __call__(self, pid, bruteforce, retry_only, upright=False):
        g = super().__call__(pid, bruteforce, retry_only, upright)
        if g is not None and pid in self.nfa:
            g.nfa = self.nfa[pid]
        return g


def test_a_track_learns_that_the_revisit_runs_backwards():
    """Queries 10 and 11 verified to stored frames 8 and 7: a route driven back. Query 12 checks
    6, 5 and then 7, and the reach around 6 goes on backwards first."""
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=3))
    policy.track.confirm(10, 8, 6, 3)
    assert policy.track.direction == 0  # one match: not known yet
    policy.track.confirm(11, 7, 6, 3)
    assert policy.track.direction == -1
    ranking = np.zeros(20)
    ranking[15] = 1.0  # FAB-MAP's best: place 15, which fails
    script = Script()
    _search(policy, 12, ranking, script)
    assert [c[0] for c in script.calls] == [6, 5, 7, 15, 4, 8, 3, 9]
    policy.track.confirm(12, 7, 6, 3)  # the same stored frame again (a robot standing): still backwards
    assert policy.track.direction == -1 and policy.track.expected(14, 6) == 5


def test_a_new_track_checks_both_ways_and_takes_the_more_significant():
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=0))
    policy.track.confirm(10, 20, 6, 3)
    script = Graded({21: -6.0, 19: -40.0})  # ahead passes, but behind is far more significant
    s = _search(policy, 11, np.zeros(40), script)
    assert [c[0] for c in script.calls] == [21, 19] and s.verified and s.best_place == 19
    assert tied_rival(s, np.arange(40), policy.config.margin_log10_nfa) is None
    policy.track.confirm(11, 19, 6, 3)
    assert policy.track.direction == -1
    # Both ways alike: which stored frame it is, is a coin toss, and the query is withheld.
    fresh = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=0))
    fresh.track.confirm(10, 20, 6, 3)
    s = _search(fresh, 11, np.zeros(40), Graded({21: -10.0, 19: -10.1}))
    assert s.best_place == 19 and tied_rival(s, np.arange(40), fresh.config.margin_log10_nfa).place == 21
    # Neither passes: the rest of the window, both ways, then the stored frame itself.
    script = Script()
    fresh = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=0))
    fresh.track.confirm(10, 20, 6, 3)
    _search(fresh, 11, np.zeros(40), script)
    assert [c[0] for c in script.calls][:5] == [21, 19, 22, 18, 20]


def test_a_new_track_at_the_maps_first_frame_checks_nothing_before_it():
    """Place ids 0-9 hold frames -1 ("none") to 8: a track at frame 0 reaches back to frame -1,
    which names no stored frame, and so no place."""
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=2))
    policy.track.confirm(10, 0, 6, 2)
    ranking = np.zeros(10)
    ranking[9] = 1.0  # FAB-MAP's best: place 9 (frame 8)
    script = Script()
    _search(policy, 11, ranking, script, frames=np.arange(-1, 9))
    # Frames 1, (-1), 2, (-2), 0 of the window; FAB-MAP's place 9; frame 3 of the reach, (-1).
    assert [c[0] for c in script.calls] == [2, 3, 1, 9, 4]


def test_a_long_gap_or_a_jump_starts_a_track_of_unknown_direction():
    policy = CandidatePolicy(CandidateConfig(track_memory=6))
    policy.track.confirm(10, 8, 6, 3)
    policy.track.confirm(11, 7, 6, 3)
    policy.track.confirm(20, 40, 6, 3)  # lag 9 > memory: a new track
    assert policy.track.direction == 0 and policy.track.expected(21, 6) == 41
    policy.track.confirm(24, 44, 6, 3)  # after a gap within memory, within reach: it goes on forwards
    assert policy.track.direction == 1
    policy.track.confirm(25, 20, 6, 3)  # 24 frames from where either way would reach: another place
    assert policy.track.direction == 0 and policy.track.anchor == 20


def test_a_step_back_does_not_turn_the_track_round():
    """Stored frames that look alike give true matches a frame or two behind the last one: the
    direction is the side of the track's first match on which a match lies, not the last step."""
    track = CandidatePolicy(CandidateConfig()).track
    for seq, frame in ((10, 20), (11, 22), (12, 24), (13, 23), (14, 22)):
        track.confirm(seq, frame, 6, 3)
    assert track.direction == 1 and track.anchor == 20
    for seq, frame in ((15, 20), (16, 19)):  # back past where it began: the revisit runs backwards
        track.confirm(seq, frame, 6, 3)
    assert track.direction == -1


def test_forwards_only_as_before_the_direction():
    """track_direction=False: every revisit is expected to run forwards, as logs and maps
    recorded before the direction was learnt."""
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=2, track_memory=6, track_reach=0, track_direction=False))
    policy.track.confirm(10, 8, 6, 3)
    policy.track.confirm(11, 7, 6, 3)
    assert policy.track.direction == 1
    script = Script()
    _search(policy, 12, np.linspace(1, 0, 20), script)
    assert [c[0] for c in script.calls] == [8, 9, 7, 0]


def test_islands_follow_a_failed_candidate():
    policy = CandidatePolicy(CandidateConfig(top_k=1, track=0, island=2, island_candidates=1))
    ranking = np.zeros(10)
    ranking[5] = 1.0
    script = Script(passes={3})
    s = _search(policy, 40, ranking, script)
    assert [c[0] for c in script.calls] == [5, 4, 6, 3] and s.source == "island"


@pytest.mark.parametrize("kw", [{"top_k": 0}, {"track": -1}, {"island": -1}, {"max_trials": 0},
                                {"max_bruteforce": -1}, {"track_memory": 0}, {"island_candidates": -1},
                                {"track_reach": 101}, {"bruteforce_fallback": -1}, {"margin_log10_nfa": -0.1},
                                {"margin_log10_nfa": float("nan")}, {"margin_log10_nfa": float("inf")}])
def test_config_is_validated(kw):
    with pytest.raises(ConfigError):
        CandidateConfig(**kw)


def _checked(*places):
    """A search over (place, log10 NFA, passed) checks, the passing one taken (as the policy does)."""
    s = Search()
    for pid, nfa, ok in places:
        g = GeometryResult(verified=ok, model="H", inliers=10 if ok else 7, nfa=nfa, reason="" if ok else "chance")
        s.attempts.append(Attempt(pid, "track", g))
        if ok:
            s.best, s.best_place = g, pid
    return s


def test_a_passing_pair_ties_with_a_stored_frame_that_is_not_its_neighbour():
    frames = np.arange(40)
    # A night query of a street: stored frame 33 passes at -5.99, but 31 (7 inliers, under the
    # floor) had -6.0 and 30 had -5.6: which stored frame it is, the evidence does not say.
    s = _checked((29, -3.0, False), (30, -5.6, False), (31, -6.0, False), (33, -5.99, True))
    rival = tied_rival(s, frames, np.log10(2))
    assert rival is not None and rival.place == 31  # the most significant of the ties
    # More than twice as unlikely by chance as every rival: taken.
    s = _checked((29, -3.0, False), (31, -5.6, False), (33, -5.99, True))
    assert tied_rival(s, frames, np.log10(2)) is None
    # A neighbouring stored frame is the same place; a check without a model is no evidence.
    s = _checked((32, -8.0, False), (34, -7.0, False), (20, np.inf, False), (33, -5.99, True))
    assert tied_rival(s, frames, np.log10(2)) is None
    # Place ids are not frames: the rival's stored frame decides.
    s = _checked((1, -6.0, False), (2, -5.99, True))
    assert tied_rival(s, np.array([0, 10, 11]), np.log10(2)) is None
    assert tied_rival(s, np.array([0, 10, 12]), np.log10(2)).place == 1
    # Margin 0 (maps journalled before it) or nothing passed: no tie.
    s = _checked((31, -6.0, False), (33, -5.99, True))
    assert tied_rival(s, frames, 0.0) is None
    assert tied_rival(_checked((31, -6.0, False)), frames, np.log10(2)) is None


@pytest.mark.parametrize("ranking, k, want", [
    (np.zeros(20), 5, [0, 1, 2, 3, 4]),
    (np.array([1.0, 3, 3, 3, 3, 3, 3, 0]), 5, [1, 2, 3, 4, 5]),
    (np.array([2.0, 1, 5, 1, 1, 1, 1, -np.inf]), 4, [2, 0, 1, 3]),
    (np.array([-np.inf, -np.inf, 0.5, -np.inf]), 3, [2, 0, 1]),
    (np.array([0.2, 0.9]), 5, [1, 0]),
])
def test_top_places_takes_the_lowest_ids_among_ties_on_every_machine(ranking, k, want):
    """argpartition alone chose and ordered tied places differently on aarch64 than on x86-64."""
    assert top_places(ranking, k).tolist() == want
