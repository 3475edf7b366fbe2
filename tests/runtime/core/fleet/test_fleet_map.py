"""Other robots' places (runtime/aefabmap_runtime/core/fleet/fleet_map.py): kept within what the own map leaves,
ranked per robot, verified as the own places are, never past the caps."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig, FleetMap
from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary
from aefabmap_runtime.core.map.map_events import MapListener

ID = bytes(32)


@pytest.fixture(scope="module")
def route():
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(12, seed=3, size=(640, 480))
    return images


def _detector():
    from aefabmap.cli.demo import default_bundle

    return load_detector(default_bundle(), DetectorConfig(exclude=1))


class _Recorder(MapListener):
    """What a detector tells its listeners: the frames it took and the places it inserted."""

    def __init__(self) -> None:
        self.taken, self.inserted = [], []

    def frame_taken(self, sequence, words, stamp_ns, features) -> None:
        self.taken.append((words, features))

    def place_inserted(self, place, frame, words, keypoints) -> None:
        self.inserted.append((frame, words, keypoints))


def _run(det, images) -> _Recorder:
    rec = _Recorder()
    det.add_listener(rec)
    try:
        for im in images:
            det.process(im)
    finally:
        det.remove_listener(rec)
    return rec


def _places_of(det, images):
    """(summary, keypoints) of every place robot "a" stores from images (as a FleetNode would publish)."""
    return [(PlaceSummary("a", ID, frame, 0, np.unique(words)), kps) for frame, words, kps in _run(det, images).inserted]


def _query(det, image):
    """(words, features) of `image` as the detector took it (its own map judged it too)."""
    return _run(det, [image]).taken[-1]


def _map(det, room=(None, None), **kw):
    return FleetMap(FleetConfig(name="f", robot="b", **kw), det.new_scorer, lambda: room)


def test_a_view_of_another_robots_place_verifies_to_that_robots_frame(route):
    a, b = _detector(), _detector()
    offered = _places_of(a, route[:6])
    fleet = _map(b)
    for summary, _ in offered:
        assert fleet.add(summary)
    kps = {s.frame: k for s, k in offered}
    fetched = []

    def fetch(pairs):
        fetched.append(list(pairs))
        return {(robot, frame): kps.get(frame) for robot, frame in pairs}

    words, features = _query(b, route[2])  # robot b's first frame: its own map is empty
    observed = words[: b.bundle.features.max_features]
    v = b.config.verification
    from dataclasses import replace

    match = fleet.match(observed, lambda bar: b.place_check(features, words, replace(v, max_log10_nfa=bar)),
                        fetch, v.max_log10_nfa)
    assert match is not None and match.robot == "a" and abs(match.frame - 2) <= 1
    assert match.geometry.nfa < v.max_log10_nfa - np.log10(match.checked)  # the stricter bar
    assert len(fetched) == 1 and fleet.robots["a"].stats.loops == 1  # every place asked for in one batch
    # Fetched keypoints are cached: the same frame again asks nobody.
    fetched.clear()
    fleet.match(observed, lambda bar: b.place_check(features, words, replace(v, max_log10_nfa=bar)), fetch,
                v.max_log10_nfa)
    assert not fetched


def test_a_fetch_that_fails_verifies_nothing_and_raises_nothing(route):
    a, b = _detector(), _detector()
    fleet = _map(b)
    for summary, _ in _places_of(a, route[:4]):
        fleet.add(summary)
    words, features = _query(b, route[1])
    observed = words[: b.bundle.features.max_features]
    assert fleet.match(observed, lambda bar: b.place_check(features, words), lambda pairs: {}, -4.0) is None


def test_remote_places_live_in_what_the_own_map_leaves(route):
    a, b = _detector(), _detector()
    offered = _places_of(a, route[:8])
    room = [3, None]
    fleet = FleetMap(FleetConfig(name="f", robot="b"), b.new_scorer, lambda: tuple(room))
    for summary, _ in offered:
        fleet.add(summary)
    assert fleet.n_places == 3 and fleet.evicted == len(offered) - 3
    assert sorted(fleet.robots["a"].place_of) == [s.frame for s, _ in offered[-3:]]  # the oldest went first
    room[0] = 1  # the own map grew
    fleet.fit()
    assert fleet.n_places == 1
    room[:] = [None, 0]  # no bytes left at all
    fleet.fit()
    assert fleet.n_places == 0


def test_refusals_are_counted_and_change_nothing(route):
    a, b = _detector(), _detector()
    offered = _places_of(a, route[:3])
    fleet = _map(b, max_robots=1)
    first = offered[0][0]
    assert fleet.add(first)
    assert not fleet.add(first)  # the same frame again (a catch-up overlapping what came live): not a refusal
    assert not fleet.add(PlaceSummary("b", ID, 99, 0, first.words))  # our own, back through a router
    assert not fleet.add(PlaceSummary("c", ID, 1, 0, first.words))  # one robot too many
    assert not fleet.add(PlaceSummary("a", ID, 50, 0, np.zeros(0, np.int64)))
    assert fleet.robots["a"].stats.refused == {"no_words": 1}
    assert fleet.robots["a"].stats.summaries == 3 and fleet.last_frame("a") == first.frame
    assert fleet.last_frame("x") == -1
    assert fleet.refused_elsewhere == {"too_many_robots": 1}
    assert list(fleet.robots) == ["a"] and fleet.n_places == 1


@pytest.mark.parametrize("bad", [dict(name="a/b"), dict(robot="*"), dict(top_k=0), dict(fetch_timeout_ms=0),
                                 dict(max_places=True)])
def test_bad_fleet_settings_are_refused(bad):
    with pytest.raises(ConfigError):
        FleetConfig(**{"name": "f", "robot": "b", **bad})


def test_the_run_configuration_keeps_the_fleet_whole():
    from aefabmap_runtime.core.run_config import RunConfig

    config = RunConfig(model="m", fleet=FleetConfig(name="lab", robot="b", fetch_timeout_ms=150))
    assert RunConfig.from_json(config.to_json()) == config
    doc = config.to_dict()
    doc["fleet"]["robot"] = "b/*"
    with pytest.raises(ConfigError):
        RunConfig.from_dict(doc)


def test_a_new_map_epoch_forgets_the_robots_places_and_cached_keypoints(route):
    from dataclasses import replace

    a, b = _detector(), _detector()
    offered = _places_of(a, route[:6])
    fleet = _map(b, max_places=6)
    for summary, _ in offered:
        fleet.add(replace(summary, epoch=1))
    kps = {s.frame: k for s, k in offered}
    first = ("a", offered[0][0].frame)
    assert first in fleet.keypoints([first], lambda pairs: {p: kps[p[1]] for p in pairs})  # cached now
    n = fleet.n_places
    assert n == len(offered) and fleet.epoch("a") == 1 and fleet.restarted == []
    # a summary of another epoch is only a claim: nothing is forgotten until a's own session confirms it
    again = replace(offered[0][0], epoch=2)
    assert not fleet.add(again)
    assert fleet.epoch_claims == {"a"} and fleet.n_places == n and fleet.restarted == []
    assert fleet.robots["a"].stats.refused == {"unconfirmed_epoch": 1}
    assert not fleet.confirm_epoch("a", 1)  # a says its epoch is the one held: nothing changes
    assert fleet.n_places == n
    # a restarted without its map: frame numbers start again and mean other places
    assert fleet.confirm_epoch("a", 2)
    assert fleet.restarted == ["a"] and fleet.epoch("a") == 2 and fleet.n_places == 0
    assert fleet.add(again)
    assert fleet.robots["a"].stats.map_restarts == 1 and fleet.last_frame("a") == again.frame
    assert fleet.keypoints([first], lambda pairs: {}) == {}  # the old keypoints are not served
    # eviction sees only the new epoch's places (the old arrivals are gone)
    for summary, _ in offered[1:]:
        fleet.add(replace(summary, epoch=2))
    assert fleet.n_places == len(offered)
    for i, (summary, _) in enumerate(offered):
        fleet.add(replace(summary, frame=100 + i, epoch=2))
    arrivals = [s.frame for s, _ in offered] + [100 + i for i in range(len(offered))]
    assert fleet.n_places == 6 and sorted(fleet.robots["a"].place_of) == sorted(arrivals[-6:])  # oldest out


def test_the_map_epoch_is_kept_in_the_state_and_drawn_anew_for_an_empty_or_older_map(route):
    a = _detector()
    _places_of(a, route[:4])
    state = a.state().resolve()
    again = _detector()
    assert again.map_epoch != a.map_epoch  # an empty map numbers its frames anew
    again.load_state(state)
    assert again.map_epoch == a.map_epoch  # a restart with --state keeps the numbering
    del state.scalars["map_epoch"]  # a state saved before epochs existed
    older = _detector()
    older.load_state(state)
    assert older.map_epoch != a.map_epoch and 0 <= older.map_epoch < 2**64


def test_after_a_loop_the_robots_next_frames_are_tried_first_and_paid_for(route):
    from dataclasses import replace

    from aefabmap_runtime.core.verify.verification import GeometryResult

    a = _detector()
    offered = _places_of(a, route[:8])
    fleet = _map(a)
    for summary, _ in offered:
        fleet.add(summary)
    frames = sorted(fleet.robots["a"].place_of)
    f = frames[2]
    fleet._matched(type("M", (), {"robot": "a", "frame": f})(), sequence=10)  # a loop of query 10 to a's frame f
    held = set(frames)
    assert fleet.tracked(11) == [("a", g) for g in (f + 1, f + 2, f) if g in held]
    assert fleet.tracked(13) == [("a", g) for g in (f + 3, f + 4, f + 2) if g in held]
    assert fleet.tracked(14) == [] and fleet.tracked(10) == []  # beyond track_memory; not a later query

    calls, bars = [], []

    def checker(bar):
        bars.append(bar)

        def check(place, bruteforce, retry_only):
            calls.append((place, retry_only))
            return replace(GeometryResult(), verified=len(calls) == 2, nfa=-9.0)  # the retry of the first passes
        return check

    kps = {s.frame: k for s, k in offered}
    observed = np.unique(offered[0][0].words)
    match = fleet.match(observed, checker, lambda pairs: {p: kps.get(p[1]) for p in pairs}, -4.0, sequence=11)
    assert match is not None and (match.robot, match.frame) == ("a", f + 1)
    assert [r for _, r in calls] == [False, True]  # by words, then all-pairs
    n_tracked = len(fleet.tracked(11))
    assert match.checked >= 2 * n_tracked and bars == [-4.0 - np.log10(match.checked)]
    assert fleet.tracked(12)[0] == ("a", f + 2)  # the track follows the new loop


def test_a_robot_is_admitted_only_while_alive_and_a_gone_one_makes_room(route):
    a, b = _detector(), _detector()
    offered = [s for s, _ in _places_of(a, route[:5])]
    fleet = _map(b, max_robots=2)
    live = {"a", "c", "d"}
    alive = live.__contains__
    assert not fleet.add(replace_robot(offered[0], "x"), alive)  # no token: a made-up robot id
    assert fleet.refused_elsewhere == {"not_alive": 1} and "x" not in fleet.robots
    assert fleet.add(offered[0], alive) and fleet.add(replace_robot(offered[1], "c"), alive)
    assert not fleet.add(replace_robot(offered[2], "d"), alive)  # table full, everyone alive
    assert fleet.refused_elsewhere["too_many_robots"] == 1
    live.discard("c")  # c left: a live newcomer takes its room, and c's places go with it
    assert fleet.add(replace_robot(offered[2], "d"), alive)
    assert sorted(fleet.robots) == ["a", "d"] and fleet.n_places == 2 and fleet.restarted == []


def test_one_robots_flood_evicts_its_own_places_not_anothers(route):
    a, b = _detector(), _detector()
    offered = [s for s, _ in _places_of(a, route[:6])]
    fleet = _map(b, max_places=6)
    for s in offered[:3]:
        fleet.add(s)
    for i in range(40):  # a peer floods under robot x
        fleet.add(replace_robot(offered[i % len(offered)], "x", frame=1000 + i))
    assert sorted(fleet.robots["a"].place_of) == [s.frame for s in offered[:3]]
    assert len(fleet.robots["x"].place_of) == 3 and sorted(fleet.robots["x"].place_of) == [1037, 1038, 1039]


def replace_robot(summary, robot, **kw):
    from dataclasses import replace

    return replace(summary, robot=robot, **kw)
