"""Per-frame detector: delayed insertion, exclusion window, caps and eviction."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap import ConfigError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.decide.sequence import SequenceConfig
from tests.conftest import make_synthetic_bundle


def words_stream(n, v=64, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, v, 40) for _ in range(n)]


@pytest.mark.parametrize("scorer", ["fabmap", "bow"])
def test_delayed_insertion_and_exclusion(synthetic_bundle, scorer):
    det = load_detector(synthetic_bundle, DetectorConfig(scorer=scorer, exclude=5))
    stream = words_stream(12)
    for i, w in enumerate(stream):
        r = det.process_words(w)
        assert r.sequence == i
        if i < 5:
            assert r.best_place is None and r.inserted_frame is None
        else:
            assert r.inserted_frame == i - 5  # frame i-5 enters the map just before query i
            assert r.best_frame <= i - 5  # never a frame inside the window
        assert r.n_places == max(0, i - 4)


def test_revisit_is_found_and_scores_are_named(synthetic_bundle):
    det = load_detector(synthetic_bundle, DetectorConfig(exclude=2))
    stream = words_stream(6, seed=1)
    for w in stream:
        det.process_words(w)
    r = det.process_words(stream[1])
    assert r.best_frame == 1 and r.score == r.probability and r.llr > 0
    det_llr = load_detector(synthetic_bundle, DetectorConfig(exclude=2, fabmap_score="llr"))
    for w in stream:
        det_llr.process_words(w)
    assert det_llr.process_words(stream[1]).score == pytest.approx(r.llr)


def test_max_places_evicts_least_recently_used(synthetic_bundle):
    det = load_detector(synthetic_bundle, DetectorConfig(exclude=0, max_places=5))
    for w in words_stream(30, seed=2):
        r = det.process_words(w)
        assert det.n_places <= 5
    assert r.evicted_place is not None
    assert det.scorer.n_places == 5  # freed ids are reused: no growth of the id range


def test_memory_cap_holds_over_a_long_run(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "b", vocabulary_size=500)
    cap_mb = 0.05
    det = load_detector(bundle, DetectorConfig(exclude=3, memory_mb=cap_mb))
    sizes = []
    for w in words_stream(3000, v=500, seed=3):
        det.process_words(w)
        sizes.append(det.map_bytes())
    assert max(sizes) <= cap_mb * 2**20
    # Flat once at the cap: the last thousand frames do not grow the map.
    assert max(sizes[-1000:]) <= max(sizes[1000:2000]) * 1.05


def test_empty_frames_still_get_results(synthetic_bundle):
    det = load_detector(synthetic_bundle, DetectorConfig(exclude=1))
    for _ in range(3):
        r = det.process_words(np.zeros(0, np.int32))
    assert r.sequence == 2 and r.n_keypoints == 0


def test_bad_config():
    with pytest.raises(ConfigError):
        DetectorConfig(scorer="dbow")
    with pytest.raises(ConfigError):
        DetectorConfig(memory_mb=0)
    with pytest.raises(ConfigError):
        DetectorConfig(fabmap_score="odds")


def test_attached_keypoints_make_a_words_only_place_verifiable():
    """A place stored from words alone is never verified; `attach_keypoints` gives it the
    keypoints a live frame would have stored, and the same view then verifies against it."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.errors import InputError
    from aefabmap_runtime.core.verify.verification import VerificationConfig
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(6, seed=0, size=(640, 480))
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    feats = [det.extractor.extract(im) for im in images]
    words = [det.words_of(f) for f in feats]
    for w in words[:3]:
        det.process_words(w[w >= 0])  # frames 0-2 as words only (the quantised keypoints); 0 and 1 are in the map now
    place = int(np.flatnonzero(det.place_frames() == 0)[0])
    assert not det.process_words(words[0], features=feats[0]).verified
    det.attach_keypoints(place, feats[0], words[0])
    r = det.process_words(words[0], features=feats[0])
    assert r.verified and r.verified_frame == 0
    with pytest.raises(InputError):
        det.attach_keypoints(10_000, feats[0], words[0])
    off = load_detector(default_bundle(), DetectorConfig(exclude=1, verification=VerificationConfig(enabled=False)))
    off.process_words(words[1][words[1] >= 0])
    off.process_words(words[2][words[2] >= 0])
    with pytest.raises(ConfigError):
        off.attach_keypoints(0, feats[0], words[0])


def test_a_chain_of_weak_pairs_verifies_the_last_frame_and_survives_a_restart(monkeypatch):
    """Two consecutive queries whose checked places (stored frames 0 and 1) each fall short alone
    pass together: the second is verified with the chain's summed NFA; a detector loaded from the
    first one's state reaches the same verdict."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.core.decide import candidates as C
    from aefabmap_runtime.core.records.map_state import MapState
    from aefabmap_runtime.core.verify.verification import GeometryResult
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(6, seed=0, size=(640, 480))

    def weak(nfa):
        return GeometryResult(verified=False, model="H", matrix=np.eye(3), inliers=7, matches=30, nfa=nfa,
                              reason="chance")

    def search(policy, seq, top, ranking, place_frames, stored, check):
        want = {3: 0, 4: 1}.get(seq)  # queries 3 and 4 each get one weak pair, to stored frames 0 and 1
        out = C.Search(tried=1)
        if want is not None and (place_frames == want).any():
            pid = int(np.flatnonzero(place_frames == want)[0])
            g = weak(-3.6)
            out.best, out.best_place, out.attempts = g, pid, [C.Attempt(pid, "fabmap", g)]
        return out

    monkeypatch.setattr(C.CandidatePolicy, "search", search)
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    results = [det.process(im) for im in images[:4]]
    assert not any(r.verified for r in results)
    saved = det.state()
    saved.resolve()
    r = det.process(images[4])
    assert r.verified and r.verified_frame == 1 and r.sequence_nfa == pytest.approx(-7.2)
    assert r.nfa == pytest.approx(-3.6) and r.geometry_reason == ""
    again = load_detector(default_bundle(), DetectorConfig(exclude=1))
    again.load_state(MapState(saved.arrays, saved.scalars))
    assert again.process(images[4]).to_dict() | {"timings_ms": {}} == r.to_dict() | {"timings_ms": {}}
    off = load_detector(default_bundle(), DetectorConfig(exclude=1, sequence=SequenceConfig(frames=0)))
    assert not [off.process(im) for im in images[:5]][-1].verified


def test_a_route_driven_back_is_followed():
    """The second lap of a generated route driven the other way: the track learns that the revisit
    runs backwards through the stored frames and follows it; a track that expects every revisit to
    run forwards (as before the direction was learnt) verifies stored frames ahead of the truth."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.core.decide.candidates import CandidateConfig
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    n = 60
    images, _ = generate_loop_sequence(n, seed=0, size=(320, 240))
    lap = n // 2
    back = list(range(lap - 1, -1, -1))  # frame lap + j of the route passes where frame j did

    def offsets(learn):
        det = load_detector(default_bundle(), DetectorConfig(exclude=lap // 2,
                                                             candidates=CandidateConfig(track_direction=learn)))
        for img in images[:lap]:
            det.process(img)
        off = [abs(r.verified_frame - j) for j in back if (r := det.process(images[lap + j])).verified]
        return np.array(off), det.policy.track.direction

    learnt, direction = offsets(True)
    forwards, _ = offsets(False)
    assert direction == -1
    assert (learnt <= 1).sum() >= 2 * (forwards <= 1).sum() > 0
    assert (learnt > 1).sum() < (forwards > 1).sum()


def test_a_pair_that_ties_with_another_stored_frame_is_withheld(monkeypatch):
    """Query 6 passes stored frame 4 (log10 NFA -5.99) after stored frame 2 fell short at -6.0:
    the evidence does not say which of the two it is, so nothing is published and the track is not
    confirmed; with a clear margin, or the margin off, the pair is taken."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.core.decide import candidates as C
    from aefabmap_runtime.core.verify.verification import GeometryResult
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(7, seed=0, size=(640, 480))
    rival_nfa = [-6.0]

    def search(policy, seq, top, ranking, place_frames, stored, check):
        out = C.Search(tried=2)
        if seq == 6:
            pid = {f: int(np.flatnonzero(place_frames == f)[0]) for f in (2, 4)}
            rival = GeometryResult(verified=False, model="H", matrix=np.eye(3), inliers=7, matches=30,
                                   nfa=rival_nfa[0], reason="chance")
            passed = GeometryResult(verified=True, model="H", matrix=np.eye(3), inliers=10, matches=31, nfa=-5.99,
                                    reason="")
            out.attempts = [C.Attempt(pid[2], "track", rival), C.Attempt(pid[4], "track", passed)]
            out.best, out.best_place = passed, pid[4]
        return out

    monkeypatch.setattr(C.CandidatePolicy, "search", search)

    def last(**candidates):
        config = DetectorConfig(exclude=1, sequence=SequenceConfig(frames=0),
                                candidates=C.CandidateConfig(**candidates))
        det = load_detector(default_bundle(), config)
        return [det.process(im) for im in images][-1], det

    r, det = last()
    assert not r.verified and not r.geometry_ok and r.geometry_reason == "tie" and r.verified_frame is None
    assert r.nfa == pytest.approx(-5.99) and det.policy.track.frame == -1
    r, det = last(margin_log10_nfa=0.0)
    assert r.verified and r.verified_frame == 4 and r.geometry_reason == "" and det.policy.track.frame == 4
    rival_nfa[0] = -5.6  # twice as likely by chance as the pair taken: no tie
    r, _ = last()
    assert r.verified and r.verified_frame == 4


def test_locate_finds_the_place_of_an_image_and_changes_nothing():
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(10, seed=3, size=(640, 480))
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    for im in images[:6]:
        det.process(im, 0)  # frames 0-4 are places
    before = (det.next_sequence, det.n_places, det.state().resolve().scalars)
    where = det.locate(det.prepare(images[3]))
    assert where.frame is not None and abs(where.frame - 3) <= 1 and where.geometry.verified and where.checked >= 1
    assert det.map.holds(where.place) and det.map.place_frames()[where.place] == where.frame
    nowhere = det.locate(det.prepare(np.zeros((480, 640), np.uint8)))
    assert nowhere.place is None and nowhere.frame is None and nowhere.geometry is None
    assert (det.next_sequence, det.n_places, det.state().resolve().scalars) == before
