"""The detector's state round trip (runtime/aefabmap_runtime/core/records/map_state.py): a run split by state() /
load_state() gives the results of the uninterrupted run, field for field; hostile states are refused."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.errors import StateError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.records.map_state import MapState
from aefabmap_runtime.tools.synthetic_route import (
    SyntheticConfig,
    generate_loop_sequence,
)
from tests.conftest import make_synthetic_bundle


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_synthetic_bundle(tmp_path_factory.mktemp("b") / "bundle", vocabulary_size=64)


@pytest.fixture(scope="module")
def route():
    images, _ = generate_loop_sequence(60, seed=3, size=(160, 120), config=SyntheticConfig(laps=2))
    return images


def _public(res) -> dict:
    d = res.to_dict()
    d.pop("timings_ms", None)
    return d


def _copy(state: MapState) -> MapState:
    state.resolve()
    return MapState({k: np.array(v, copy=True) for k, v in state.arrays.items()}, dict(state.scalars))


CONFIGS = {
    "fabmap-verified-capped": DetectorConfig(exclude=5, max_places=45, temporal_frames=1),
    "fabmap-motion-memory": DetectorConfig(exclude=5, motion_model=True, memory_mb=0.12),
    "bow": DetectorConfig(scorer="bow", exclude=5, max_places=45),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_split_run_is_bit_identical(bundle, route, name):
    config = CONFIGS[name]
    whole = load_detector(bundle, config)
    expected = [_public(whole.process(img, i)) for i, img in enumerate(route)]
    assert any(r["loop"] for r in expected)
    assert any(r["evicted_place"] is not None for r in expected)

    first = load_detector(bundle, config)
    half = 33  # inside the revisit: track prior, temporal history and insertion queue all in use
    got = [_public(first.process(img, i)) for i, img in enumerate(route[:half])]
    state = _copy(first.state())
    second = load_detector(bundle, config)
    second.load_state(state)
    got += [_public(second.process(img, i + half)) for i, img in enumerate(route[half:])]
    assert got == expected
    assert second.map_bytes() == whole.map_bytes()


def _state(bundle, route, config=CONFIGS["fabmap-verified-capped"], frames: int = 40) -> MapState:
    det = load_detector(bundle, config)
    for i, img in enumerate(route[:frames]):
        det.process(img, i)
    return _copy(det.state())


def _refused(bundle, state, config=CONFIGS["fabmap-verified-capped"]) -> str:
    with pytest.raises(StateError) as info:
        load_detector(bundle, config).load_state(state)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def test_hostile_states_are_refused(bundle, route):
    good = _state(bundle, route)
    s = _copy(good)
    s.arrays["scorer.places.postings"][0] = 10**6
    assert "postings" in _refused(bundle, s)
    s = _copy(good)
    s.arrays["scorer.places.words"][-1] = 64  # word id = vocabulary size
    assert "words" in _refused(bundle, s)
    s = _copy(good)
    s.arrays["store.word"] = s.arrays["store.word"][:-1]
    assert "store" in _refused(bundle, s) or "ptr" in _refused(bundle, s)
    s = _copy(good)
    s.arrays["place_frame"] = s.arrays["place_frame"].astype(np.float32)
    assert "place_frame" in _refused(bundle, s)
    s = _copy(good)
    s.arrays["scorer.places.free"] = np.array([0], np.int64)
    assert "free" in _refused(bundle, s)
    s = _copy(good)
    s.scalars["sequence"] = -1
    assert "sequence" in _refused(bundle, s)
    s = _copy(good)
    del s.arrays["last_used"]
    assert "last_used" in _refused(bundle, s)
    assert "scorer" in _refused(bundle, _copy(good), CONFIGS["bow"])
    for name, value in (("track_direction", 2), ("track_direction", -2), ("track_direction", True),
                        ("track_direction", 0.5), ("track_anchor", -2), ("track_anchor", 10**9)):
        s = _copy(good)
        s.scalars[name] = value
        assert name in _refused(bundle, s)


def test_the_tracks_direction_survives_a_split_and_an_old_map_learns_it_anew(bundle, route):
    """A route whose second lap is driven back: split inside it, the run goes on as the whole run,
    the track running backwards. A map saved before the track had a direction loads (not known yet);
    a forwards-only detector refuses a state whose track runs backwards."""
    import dataclasses

    from aefabmap_runtime.core.decide.candidates import CandidateConfig

    back = route[:30] + route[30:][::-1]
    config = CONFIGS["fabmap-verified-capped"]
    whole = load_detector(bundle, config)
    expected = [_public(whole.process(img, i)) for i, img in enumerate(back)]
    first = load_detector(bundle, config)
    half = 47  # two verified matches back along the route: the track runs backwards
    got = [_public(first.process(img, i)) for i, img in enumerate(back[:half])]
    assert first.policy.track.direction == -1
    state = _copy(first.state())
    second = load_detector(bundle, config)
    second.load_state(_copy(state))
    got += [_public(second.process(img, i + half)) for i, img in enumerate(back[half:])]
    assert got == expected
    old = _copy(state)
    del old.scalars["track_direction"], old.scalars["track_anchor"]
    again = load_detector(bundle, config)
    again.load_state(old)
    track = again.policy.track
    assert track.direction == 0 and track.frame == track.anchor == first.policy.track.frame
    forwards = dataclasses.replace(config, candidates=CandidateConfig(track_direction=False))
    assert "direction" in _refused(bundle, _copy(state), forwards)
    load_detector(bundle, forwards).load_state(old)  # an old map ran forwards: it loads


def test_a_map_saved_with_a_smaller_verification_budget_loads_and_keeps_working(bundle, route):
    """A map of an earlier version (verification on the bundle's own budget) is not lost when the
    verification budget grows; a map whose places hold more keypoints than the cap is refused."""
    import dataclasses

    from aefabmap_runtime.core.verify.verification import VerificationConfig

    def config(keypoints):
        return dataclasses.replace(CONFIGS["fabmap-verified-capped"], verification=VerificationConfig(keypoints=keypoints))

    split = 30  # the end of the first lap: the second lap's revisits all come after the restart
    small = _state(bundle, route, config(None), frames=split)
    det = load_detector(bundle, config(900))
    det.load_state(_copy(small))
    results = [det.process(img, split + i) for i, img in enumerate(route[split:])]
    assert any(r.verified for r in results)  # the second lap still closes loops onto stored places
    big = _state(bundle, route, config(900))
    assert "keypoint counts" in _refused(bundle, big, config(150))


def test_a_state_packs_the_map_it_was_taken_of_even_after_more_frames(bundle, route):
    """The keypoints are packed late (MapState.resolve, in the snapshot thread): frames processed
    in between (evicting places, reusing their ids) must not leak into it."""
    det = load_detector(bundle, CONFIGS["fabmap-verified-capped"])
    for i, img in enumerate(route[:50]):
        det.process(img, i)
    taken = det.state()
    now = _copy(det.state())
    evicted = [det.process(img, i).evicted_place for i, img in enumerate(route[50:], 50)]
    assert any(e is not None for e in evicted)
    taken.resolve()
    assert taken.arrays.keys() == now.arrays.keys()
    assert all(np.array_equal(taken.arrays[k], now.arrays[k]) for k in now.arrays)


def test_settings_recorded_before_upright_descriptors_match_a_run_without_them():
    """A map state or journal written before upright descriptors existed recorded no such
    setting; those maps ran without them, so they resume with `--no-verify-upright` and are
    named as different from a run with them."""
    import dataclasses
    import json

    from aefabmap_runtime.core.run_config import recorded_settings_differences
    from aefabmap_runtime.core.verify.verification import VerificationConfig

    now = DetectorConfig()
    old = now.to_dict()
    del old["verification"]["upright"]
    without = dataclasses.replace(now, verification=VerificationConfig(upright=False))
    assert recorded_settings_differences(json.dumps(old), without) == []
    assert recorded_settings_differences(json.dumps(old), now) == ["verification.upright"]
    assert recorded_settings_differences(json.dumps(now.to_dict()), now) == []


def test_settings_recorded_before_the_retry_alone_match_a_run_with_same_word_checks_first():
    import dataclasses
    import json

    from aefabmap_runtime.core.decide.candidates import CandidateConfig
    from aefabmap_runtime.core.run_config import recorded_settings_differences

    now = DetectorConfig()
    old = now.to_dict()
    del old["candidates"]["retry_alone"]
    before = dataclasses.replace(now, candidates=CandidateConfig(retry_alone=False))
    assert recorded_settings_differences(json.dumps(old), before) == []
    assert recorded_settings_differences(json.dumps(old), now) == ["candidates.retry_alone"]
