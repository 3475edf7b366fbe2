"""Geometric verification, keypoint store and temporal filter (pure, generated data)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from aefabmap import ConfigError
from aefabmap_runtime.errors import StateError
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
from aefabmap_runtime.core.map.keypoint_store import PLACE_OVERHEAD_BYTES, KeypointStore
from aefabmap_runtime.core.decide.temporal import TemporalFilter
from aefabmap_runtime.core.verify.verification import (
    NO_WORD,
    UPRIGHT_LOG10_TESTS,
    GeometryResult,
    VerificationConfig,
    estimate_geometry,
    match_keypoints,
    symmetric_epipolar_distance,
    verify_pair,
    verify_pair_bruteforce,
)


def texture(seed: int, size=(480, 360)) -> np.ndarray:
    """A cluttered gray image: random rectangles, circles and lines on smoothed noise."""
    w, h = size
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w)).astype(np.uint8), (0, 0), 3)
    for _ in range(120):
        kind = rng.integers(3)
        c = int(rng.integers(0, 256))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 60)), y + int(rng.integers(5, 60))), c, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), int(rng.integers(3, 30)), c, -1)
        else:
            cv2.line(img, (x, y), (int(rng.integers(0, w)), int(rng.integers(0, h))), c, int(rng.integers(1, 4)))
    return img


PERSPECTIVE = np.array([[0.9, 0.08, 30.0], [-0.05, 0.95, 12.0], [1e-4, -5e-5, 1.0]])


@pytest.fixture(scope="module")
def extractor():
    return FeatureExtractor(FeatureConfig(kind="orb", max_features=500, long_side=None))


def one_word(feats) -> np.ndarray:
    """Every keypoint in word 0: same-word matching becomes plain brute force."""
    return np.zeros(len(feats), np.int64)


def test_warped_texture_verifies_and_returns_the_homography(extractor):
    place = texture(1)
    query = cv2.warpPerspective(place, PERSPECTIVE, (place.shape[1], place.shape[0]))
    fp, fq = extractor.extract(place), extractor.extract(query)
    g = verify_pair(fq.keypoints, one_word(fq), fq.descriptors, fq.image_shape,
                    fp.keypoints, one_word(fp), fp.descriptors, fp.image_shape, VerificationConfig(), distance="hamming")
    assert g.verified and g.inliers >= 50 and g.model == "H"
    assert g.nfa < -30 and g.reason == ""  # far beyond chance: NFA << 1
    # The matrix maps the place image to the query image in pixels: compare with the warp.
    pts = np.array([[100.0, 100.0, 1.0], [300.0, 200.0, 1.0], [200.0, 300.0, 1.0]])
    est = pts @ g.matrix.T
    true = pts @ PERSPECTIVE.T
    err = np.linalg.norm(est[:, :2] / est[:, 2:] - true[:, :2] / true[:, 2:], axis=1)
    assert err.max() < 3.0


def test_unrelated_textures_do_not_verify(extractor):
    cfg = VerificationConfig()
    for a, b in [(1, 2), (3, 4), (5, 6)]:
        fa, fb = extractor.extract(texture(a)), extractor.extract(texture(b))
        g = verify_pair(fa.keypoints, one_word(fa), fa.descriptors, fa.image_shape,
                        fb.keypoints, one_word(fb), fb.descriptors, fb.image_shape, cfg, distance="hamming")
        # Whatever the estimator fitted is within chance: NFA >= 1.
        assert not g.verified and g.nfa >= 0 and g.reason in ("chance", "degenerate", "no_evidence")


def test_fundamental_matrix_of_a_3d_scene_is_in_pixels():
    """Two views of random 3-D points (not planar): F is found and x_q^T F x_p ~ 0 in pixels."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-4, 4, 200), rng.uniform(-3, 3, 200), rng.uniform(6, 20, 200)]
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    R, _ = cv2.Rodrigues(np.array([0.0, 0.15, 0.02]))
    t = np.array([1.0, 0.1, 0.3])

    def project(P):
        x = P @ K.T
        return x[:, :2] / x[:, 2:]

    xp = project(X)
    xq = project(X @ R.T + t) + rng.normal(0, 0.3, (200, 2))
    cfg = VerificationConfig(min_inliers_h=1000)  # force the F path
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
    assert g.verified and g.model == "F" and g.inliers > 180
    assert np.median(symmetric_epipolar_distance(g.matrix, xq, xp)) < 1.0


def test_matching_is_restricted_to_words_mutual_and_ratio_tested(kernels):
    rng = np.random.default_rng(0)
    desc = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    words = np.arange(50) % 5
    pairs = match_keypoints(words, desc, words, desc.copy(), VerificationConfig(), distance="hamming")
    assert len(pairs) == 50 and np.array_equal(pairs[:, 0], pairs[:, 1])
    # Different words never match, even with identical descriptors.
    assert len(match_keypoints(words, desc, (words + 1) % 5 + 10, desc, VerificationConfig(), distance="hamming")) == 0
    # Two equally near place descriptors: the ratio test rejects the ambiguous match.
    q = desc[:1]
    p = np.vstack([desc[:1], desc[:1]])
    assert len(match_keypoints(np.zeros(1), q, np.zeros(2), p, VerificationConfig(), distance="hamming")) == 0


def test_too_few_matches_and_empty_inputs_do_not_verify():
    cfg = VerificationConfig()
    g = estimate_geometry(np.zeros((3, 2)), np.zeros((3, 2)), (100, 100), (100, 100), cfg)
    assert not g.verified and g.matches == 3
    empty = np.zeros((0, 2), np.float32)
    g = verify_pair(empty, np.zeros(0, np.int64), np.zeros((0, 32), np.uint8), (10, 10),
                    empty, np.zeros(0, np.int64), np.zeros((0, 32), np.uint8), (10, 10), cfg, distance="hamming")
    assert not g.verified


def test_config_is_validated():
    with pytest.raises(ConfigError):
        CandidateConfig(top_k=0)
    with pytest.raises(ConfigError):
        VerificationConfig(method="lmeds")
    with pytest.raises(ConfigError):
        VerificationConfig(min_inliers=3)


def test_keypoint_store_round_trip_and_bytes():
    store = KeypointStore(get_kind("orb"), vocabulary_size=2000, max_keypoints=300)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, [640, 480], (500, 2)).astype(np.float32)
    words = rng.integers(0, 2000, 500)
    desc = rng.integers(0, 256, (500, 32), dtype=np.uint8)
    place = store.pack(xy, words, desc, (480, 640))
    assert len(place) == 300 and store.bytes_per_keypoint == 38
    assert np.abs(place.xy - xy[:300]).max() < 0.01  # 1/65535 of the long side
    assert np.array_equal(place.words, words[:300]) and np.array_equal(place.descriptors, desc[:300])
    store.put(7, place)
    assert store.nbytes() == 300 * 38 + PLACE_OVERHEAD_BYTES and 7 in store
    store.put(7, place)  # replacing does not double count
    assert store.nbytes() == 300 * 38 + PLACE_OVERHEAD_BYTES
    store.remove(7)
    assert store.nbytes() == 0 and store.get(7) is None


def test_keypoint_store_keeps_upright_descriptors_and_counts_their_bytes():
    store = KeypointStore(get_kind("orb"), vocabulary_size=2000, max_keypoints=300)
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, [640, 480], (500, 2)).astype(np.float32)
    words = rng.integers(0, 2000, 500)
    desc, up = rng.integers(0, 256, (2, 500, 32), dtype=np.uint8)
    place = store.pack(xy, words, desc, (480, 640), up)
    assert np.array_equal(place.upright, up[:300]) and np.array_equal(place.descriptors, desc[:300])
    store.put(3, place)
    assert store.nbytes() == 300 * (38 + 32) + PLACE_OVERHEAD_BYTES
    with pytest.raises(Exception, match=r"upright descriptors \(10\) differ in count"):
        store.pack(xy, words, desc, (480, 640), up[:10])


def _places_with_and_without_upright():
    store = KeypointStore(get_kind("orb"), vocabulary_size=100)
    rng = np.random.default_rng(5)

    def place(n, upright):
        d = rng.integers(0, 256, (2, n, 32), dtype=np.uint8)
        return store.pack(rng.uniform(0, 100, (n, 2)), rng.integers(0, 100, n), d[0], (100, 100),
                          d[1] if upright else None)

    return store, [place(4, True), None, place(3, False), place(5, True)]


def test_upright_descriptors_survive_the_state_and_old_states_have_none():
    store, places = _places_with_and_without_upright()
    st = store.pack_places(places)
    back = store.unpack_places(st, 4)
    assert back[1] is None and back[2].upright is None
    for i in (0, 3):
        assert np.array_equal(back[i].upright, places[i].upright)
        assert np.array_equal(back[i].descriptors, places[i].descriptors)
    # A state written before places held upright descriptors: same places, none of them upright.
    del st.arrays["upright"], st.arrays["has_upright"]
    assert all(p is None or p.upright is None for p in store.unpack_places(st, 4))


@pytest.mark.parametrize("damage", ["rows", "width", "flag_without_place", "flags_shape", "dtype", "one_array"])
def test_hostile_upright_state_is_refused(damage):
    store, places = _places_with_and_without_upright()
    st = store.pack_places(places)
    if damage == "rows":
        st.arrays["upright"] = st.arrays["upright"][:-1]
    elif damage == "width":
        st.arrays["upright"] = st.arrays["upright"][:, :16]
    elif damage == "flag_without_place":
        st.arrays["has_upright"][1] = True
    elif damage == "flags_shape":
        st.arrays["has_upright"] = st.arrays["has_upright"][:3]
    elif damage == "dtype":
        st.arrays["upright"] = st.arrays["upright"].astype(np.float32)
    else:
        del st.arrays["has_upright"]
    with pytest.raises(StateError):
        store.unpack_places(st, 4)


def test_geometry_only_keypoints_are_stored_and_skipped_by_same_word_matching(kernels):
    rng = np.random.default_rng(2)
    desc = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    words = np.array([3, 3, NO_WORD, 7, NO_WORD, NO_WORD])
    for vocabulary in (2000, 70000):  # uint16 and int32 word ids
        store = KeypointStore(get_kind("orb"), vocabulary_size=vocabulary)
        place = store.pack(rng.uniform(0, 100, (6, 2)), words, desc, (100, 100))
        assert np.array_equal(place.words, words)
        st = store.pack_places([place])
        (back,) = store.unpack_places(st, 1)
        assert np.array_equal(back.words, words)
        st.arrays["word"][0] = vocabulary  # outside the vocabulary, and not the no-word code
        with pytest.raises(StateError):
            store.unpack_places(st, 1)
    # Identical descriptors: only the pairs that share a real word match.
    pairs = match_keypoints(words, desc, words, desc, VerificationConfig(ratio=1.0), distance="hamming")
    assert sorted(pairs[:, 0].tolist()) == [0, 1, 3]


def test_sift_descriptors_are_stored_as_bytes_and_still_match():
    rng = np.random.default_rng(1)
    d = rng.random((40, 128)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sift = get_kind("sift")
    c = sift.compress(d)
    assert c.dtype == np.uint8 and c.shape == (40, 128)
    pairs = match_keypoints(np.zeros(40), d, np.zeros(40), c, VerificationConfig(ratio=0.95), distance=sift.distance)
    assert len(pairs) == 40 and np.array_equal(pairs[:, 0], pairs[:, 1])


def test_temporal_filter_needs_consecutive_agreement():
    f = TemporalFilter(frames=2, tolerance=5)
    assert [f.update(m) for m in (100, 101, 103, None, 105, 106, 107, 300)] == [
        False, False, True, False, False, False, True, False,
    ]
    assert TemporalFilter(0, 0).update(3) and not TemporalFilter(0, 0).update(None)


# --- the detector with verification ----------------------------------------------------------


def _detector(tmp_path, **kw):
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "b", vocabulary_size=64)
    return load_detector(bundle, DetectorConfig(exclude=2, fabmap_score="llr", **kw))


def test_detector_verifies_a_revisit_and_every_frame_gets_a_result(tmp_path):
    det = _detector(tmp_path)
    frames = [texture(s) for s in range(10, 15)]
    revisit = cv2.warpPerspective(frames[1], PERSPECTIVE, (480, 360))
    blank = np.full((360, 480), 128, np.uint8)  # a blank wall: no keypoints
    results = [det.process(f) for f in frames + [blank, revisit]]
    assert [r.sequence for r in results] == list(range(7))
    assert all(not r.verified for r in results[:-1])
    assert results[5].n_keypoints == 0 and results[5].verified is False
    # A texture-poor frame is a miss for lack of evidence, not a rejected loop.
    assert results[5].geometry_reason == "no_evidence" and results[5].nfa is None
    r = results[-1]
    # Inliers count once per descriptor window (`VerificationConfig.independence`).
    assert r.verified and r.loop and r.verified_frame == 1 and r.inliers >= 15
    assert r.geometry_reason == "" and r.nfa is not None and r.nfa < -15
    assert r.geometry_model in ("F", "H") and np.asarray(r.geometry).shape == (3, 3)
    assert "verification" in r.timings_ms
    doc = json.loads(json.dumps(r.to_dict()))  # the Zenoh/MCAP message carries it
    assert doc["verified"] is True and doc["inliers"] == r.inliers and doc["nfa"] == r.nfa


def test_fabmap_observes_the_bundle_budget_and_verification_matches_more(tmp_path):
    """The bundle was trained on its strongest max_features keypoints: FAB-MAP sees exactly those
    words; the store and the geometric test get the larger verification budget."""
    from aefabmap_runtime.core.verify.verification import VerificationConfig as VC

    det = _detector(tmp_path, verification=VC(keypoints=900))
    budget = det.bundle.features.max_features
    assert budget < 900 and det.extractor.config.max_features == 900
    frame = texture(5)
    feats = det.extractor.extract(frame)
    assert len(feats) > budget  # the texture has more corners than the bundle's budget
    words = det.words_of(feats)
    # Only the budget is quantised: the rest are matched by the brute-force retry alone.
    assert np.all(words[:budget] >= 0) and np.all(words[budget:] == NO_WORD)
    seen = []
    det.scorer.rank = lambda w, _rank=det.scorer.rank: (seen.append(np.asarray(w).copy()), _rank(w))[1]
    r = det.process(frame)
    assert r.n_keypoints == len(feats) and np.array_equal(seen[-1], words[:budget])
    assert r.n_words == np.unique(words[:budget]).size
    assert len(det.map.queued()[-1][2]) == len(feats) and np.array_equal(det.map.queued()[-1][1], words[:budget])
    # With the verification budget at the bundle's, nothing more is extracted.
    small = _detector(tmp_path / "small", verification=VC(keypoints=None))
    assert small.extractor.config.max_features == budget
    with pytest.raises(ConfigError):
        VC(keypoints=4)


def test_store_is_in_map_bytes_and_evicted_places_leave_it(tmp_path):
    det = _detector(tmp_path, max_places=3)
    base = det.map_bytes()
    for s in range(20, 28):
        det.process(texture(s))
    assert len(det.store) == det.n_places == 3
    assert set(det.store._places) <= set(np.flatnonzero(det.scorer.alive))
    assert det.map_bytes() >= base + det.store.nbytes() > base


def test_verification_can_be_switched_off(tmp_path):
    from aefabmap_runtime.core.verify.verification import VerificationConfig as VC

    det = _detector(tmp_path, verification=VC(enabled=False))
    r = det.process(texture(1))
    assert det.store is None and r.verified is False and "verification" not in r.timings_ms
    with pytest.raises(ConfigError):
        _detector(tmp_path / "x", verification=VC(enabled=False), temporal_frames=2)


def test_results_are_deterministic(tmp_path):
    frames = [texture(s) for s in range(30, 34)] + [cv2.warpPerspective(texture(30), PERSPECTIVE, (480, 360))]
    runs = []
    for k in range(2):
        det = _detector(tmp_path / str(k))
        runs.append([{k2: v for k2, v in det.process(f).to_dict().items() if k2 != "timings_ms"} for f in frames])
    assert runs[0] == runs[1]


# --- real data (skipped when the data sets are absent, docs/data.md) --------------------------


def _camvid_pairs(train_images):
    by_drive: dict[str, list] = {}
    for p in train_images:
        by_drive.setdefault(p.name.split("_")[0], []).append(p)
    drives = sorted(by_drive)
    positives = [(by_drive[d][k], by_drive[d][k + 1]) for d in drives for k in (10, 40)]
    negatives = [(by_drive[a][k], by_drive[b][k]) for a, b in zip(drives, drives[1:] + drives[:1]) for k in (10, 40)]
    return positives, negatives


@pytest.mark.slow
def test_default_thresholds_on_training_street_pairs(train_images):
    """Frames 1 s apart in a camvid drive mostly verify; frames of different drives never do."""
    if len(train_images) < 100:
        pytest.skip("camvid training images not found")
    ex = FeatureExtractor(FeatureConfig(kind="orb", max_features=500))
    cfg = VerificationConfig()
    positives, negatives = _camvid_pairs(train_images)

    def check(a, b):
        fa, fb = ex.extract(load_image(a)), ex.extract(load_image(b))
        return verify_pair(fa.keypoints, one_word(fa), fa.descriptors, fa.image_shape,
                           fb.keypoints, one_word(fb), fb.descriptors, fb.image_shape, cfg, distance="hamming")

    pos = [check(a, b).verified for a, b in positives]
    neg = [check(a, b) for a, b in negatives]
    assert sum(pos) >= len(pos) - 2, pos
    assert not any(g.verified for g in neg), [(g.f_inliers, g.h_inliers) for g in neg]


def test_every_lip6_frame_gets_a_result(lip6, tmp_path):
    from aefabmap_runtime.adapters.frames import load_image
    from aefabmap_runtime.adapters.image_folder import list_images

    det = _detector(tmp_path)
    images = list_images(lip6)[:12]
    results = [det.process(load_image(p)) for p in images]
    assert [r.sequence for r in results] == list(range(12))
    assert all(isinstance(r.verified, bool) and "verification" in r.timings_ms for r in results)


def test_memory_cap_counts_the_keypoint_store(tmp_path):
    cap_mb = 0.08  # a few places of ~19 kB of ORB keypoints each
    det = _detector(tmp_path, memory_mb=cap_mb)
    evicted = []
    for s in range(40, 52):
        r = det.process(texture(s, size=(320, 240)))
        evicted.append(r.evicted_place)
        assert det.map_bytes() <= cap_mb * 2**20
        assert len(det.store) == det.n_places  # evicted places left the store
    assert any(e is not None for e in evicted) and det.store.nbytes() > 0


# --- candidate generation: track prior, island, trial cap ----------------------------------------


def _one_word_run(tmp_path, images, **candidates):
    """Run images through a detector where every keypoint has word 0: FAB-MAP then ties every
    place (top_k=1 picks place 0, the first frame) and same-word matching is brute force, so
    only the track prior / island can find any other place."""
    from aefabmap_runtime.core.decide.candidates import CandidateConfig

    det = _detector(tmp_path, candidates=CandidateConfig(**{"top_k": 1, **candidates}))
    ex = FeatureExtractor(FeatureConfig(kind="orb", max_features=500, long_side=None))
    out = []
    for img in images:
        f = ex.extract(img)
        out.append(det.process_words(one_word(f).astype(np.int32), features=f))
    return det, out


def _revisit_sequence():
    base = [texture(s) for s in range(60, 66)]
    warp = [cv2.warpPerspective(b, PERSPECTIVE, (480, 360)) for b in base]
    return base + [warp[0], warp[1], warp[2], texture(99), warp[3]]


def test_track_prior_follows_a_revisit_that_fabmap_ranks_low(tmp_path):
    _, r = _one_word_run(tmp_path, _revisit_sequence(), track=2, track_memory=1)
    assert r[6].verified and r[6].verified_frame == 0  # found by FAB-MAP (place 0)
    # The next frames continue where the last one matched: one trial each.
    assert r[7].verified and r[7].verified_frame == 1 and r[7].candidates_tried == 1
    assert r[8].verified and r[8].verified_frame == 2 and r[8].candidates_tried == 1
    # An unrelated frame: the tracked places are tried and fail (no false loop); with a memory
    # of one frame that ends the track, so the frame after it has FAB-MAP's candidate only.
    assert not r[9].verified and r[9].candidates_tried >= 2
    assert not r[10].verified and r[10].candidates_tried == 1


def test_track_memory_bridges_a_failed_frame(tmp_path):
    _, r = _one_word_run(tmp_path, _revisit_sequence(), track=2, track_memory=3)
    assert not r[9].verified
    # Two frames after the last match (frame 2): frame 2 + 2 = 4 is expected, 3 is tried after.
    assert r[10].verified and r[10].verified_frame == 3


def _skip_ahead_sequence():
    """Six places, a revisit of place 0, then a jump to place 4 (the robot moved faster than
    the track expects: frame 0 + 1 is expected, its window is 1, 2 and 0)."""
    seq = _revisit_sequence()
    return seq[:7] + [cv2.warpPerspective(texture(64), PERSPECTIVE, (480, 360))]


def test_track_reach_finds_a_revisit_beyond_the_track_window(tmp_path):
    _, r = _one_word_run(tmp_path, _skip_ahead_sequence(), track=2, track_memory=1, track_reach=3)
    assert r[6].verified and r[6].verified_frame == 0
    # Window 1, 2, 0 and FAB-MAP's place 0 fail; then within reach, nearest first: 3, then 4.
    assert r[7].verified and r[7].verified_frame == 4 and r[7].candidates_tried == 5


def test_track_reach_zero_stops_at_the_track_window(tmp_path):
    _, r = _one_word_run(tmp_path, _skip_ahead_sequence(), track=2, track_memory=1, track_reach=0)
    assert r[6].verified and r[6].verified_frame == 0
    assert not r[7].verified and r[7].candidates_tried == 3


def test_track_reach_never_reaches_past_its_frames(tmp_path):
    seq = _skip_ahead_sequence()[:7] + [cv2.warpPerspective(texture(65), PERSPECTIVE, (480, 360))]
    _, r = _one_word_run(tmp_path, seq, track=2, track_memory=1, track_reach=3)
    assert not r[7].verified  # place 5 lies 4 frames past the expected frame 1
    _, r = _one_word_run(tmp_path / "wider", seq, track=2, track_memory=1, track_reach=4)
    assert r[7].verified and r[7].verified_frame == 5


def test_track_reach_retries_by_brute_force_a_place_fabmap_checked_by_same_word_only(tmp_path, monkeypatch):
    """A FAB-MAP candidate past `bruteforce_fallback` is checked by same-word matching only.
    When that fails (here every same-word check is made to fail) and the place lies within the
    track's reach, the reach checks it again with the brute-force retry: the reach's rule is
    "each with the retry", whatever checked the place before."""
    from aefabmap_runtime.core import detector as detector_module

    real, real_retry = detector_module.verify_pair, detector_module.verify_pair_bruteforce
    retries_alone: list[int] = []

    def same_word_fails(*args, bruteforce=False, **kw):
        if not bruteforce:
            return GeometryResult()
        return real(*args, bruteforce=True, **kw)

    def retry_alone(*args, **kw):
        retries_alone.append(1)
        return real_retry(*args, **kw)

    monkeypatch.setattr(detector_module, "verify_pair", same_word_fails)
    monkeypatch.setattr(detector_module, "verify_pair_bruteforce", retry_alone)
    # All words tie, so FAB-MAP ranks places 0, 1, 2, 3, 4; the track (expected frame 1) has
    # already tried 1, 2 and 0 with the retry; 3 and 4 get same-word checks only (ranks 3, 4).
    for reach, found in ((3, True), (0, False)):
        retries_alone.clear()
        _, r = _one_word_run(tmp_path / str(reach), _skip_ahead_sequence(), track=2, track_memory=1,
                             track_reach=reach, top_k=5, bruteforce_fallback=1, retry_alone=False)
        assert r[6].verified and r[6].verified_frame == 0
        assert r[7].verified == found
        if found:
            # Track window 1, 2, 0; FAB-MAP 3, 4 (same word); reach: the retry alone for 3, then
            # for 4, whose same-word checks already failed: five places, each counted once.
            assert r[7].verified_frame == 4 and r[7].candidates_tried == 5
            assert len(retries_alone) == 2
        else:
            assert not retries_alone


def test_without_track_fabmap_candidates_alone_miss_it(tmp_path):
    _, r = _one_word_run(tmp_path, _revisit_sequence(), track=0)
    assert r[6].verified and r[6].verified_frame == 0
    assert not r[7].verified and not r[8].verified


def test_island_tries_the_temporal_neighbours_of_a_failed_candidate(tmp_path):
    seq = _revisit_sequence()
    _, r = _one_word_run(tmp_path, seq[:6] + [seq[7]], track=0, island=1)
    assert r[6].verified and r[6].verified_frame == 1 and r[6].candidates_tried == 2
    _, r = _one_word_run(tmp_path / "cap", seq[:6] + [seq[7]], track=0, island=1, max_trials=1)
    assert not r[6].verified and r[6].candidates_tried == 1


def test_bruteforce_retries_per_frame_are_capped(tmp_path, monkeypatch):
    from aefabmap_runtime.core import detector as detector_module

    flags: list[list[bool]] = []
    real = detector_module.verify_pair

    def spy(*args, bruteforce=False, **kw):
        flags[-1].append(bool(bruteforce))
        return real(*args, bruteforce=bruteforce, **kw)

    monkeypatch.setattr(detector_module, "verify_pair", spy)
    seq = _revisit_sequence()
    for cap, most in ((None, None), (1, 1), (0, 0)):
        flags.clear()
        det = _detector(tmp_path / str(cap), candidates=CandidateConfig(max_bruteforce=cap))
        for img in seq:
            flags.append([])
            det.process(img)
        # After the verified revisit frames, the unrelated frame (index 9) retries its tracked
        # places and its best FAB-MAP candidate by brute force, up to the cap.
        counts = [sum(f) for f in flags]
        assert counts[9] >= 2 if most is None else max(counts) == most


def test_bruteforce_retry_uses_the_same_acontrario_criterion(extractor):
    place = texture(1)
    query = cv2.warpPerspective(place, PERSPECTIVE, (place.shape[1], place.shape[0]))
    fp, fq = extractor.extract(place), extractor.extract(query)
    # Disjoint word ids: same-word matching finds nothing, only the brute-force retry can.
    qw, pw = np.zeros(len(fq), np.int64), np.ones(len(fp), np.int64)

    def run(**kw):
        return verify_pair(fq.keypoints, qw, fq.descriptors, fq.image_shape, fp.keypoints, pw, fp.descriptors,
                           fp.image_shape, VerificationConfig(**kw), bruteforce=True, distance="hamming")

    assert not verify_pair(fq.keypoints, qw, fq.descriptors, fq.image_shape, fp.keypoints, pw, fp.descriptors,
                           fp.image_shape, VerificationConfig(), distance="hamming").verified
    g = run()
    assert g.verified and g.nfa < -30
    # The same matches against a significance bar they do not reach: rejected.
    strict = run(max_log10_nfa=g.nfa - 1.0)
    assert not strict.verified and strict.reason == "chance"


def test_verification_config_is_validated():
    for kw in ({"ratio_bruteforce": 0.0}, {"min_inliers_h": 3}, {"min_f_sigma_ratio": 1.0},
               {"h_max_scale": 0.5}, {"min_extent": 1.0}, {"max_log10_nfa": float("nan")},
               {"camera": "1,2,3"}, {"camera": (0.0, 1.0, 2.0, 3.0)}, {"camera": "a,b,c,d"}):
        with pytest.raises(ConfigError):
            VerificationConfig(**kw)


def _upright_pair():
    """A textured view and a warped view of it, with upright descriptors, as the detector extracts."""
    ex = FeatureExtractor(FeatureConfig("orb", 1000), upright=True)
    a = ex.extract(texture(21))
    b = ex.extract(cv2.warpPerspective(texture(21), PERSPECTIVE, (480, 360)))
    return a, b


def test_extra_tests_raise_every_models_nfa_and_can_reject_it(kernels):
    from aefabmap_runtime.core.verify.verification import match_all

    a, b = _upright_pair()
    c = VerificationConfig()
    pairs = match_all(a.descriptors, b.descriptors, c, distance="hamming")
    args = (a.keypoints[pairs[:, 0]], b.keypoints[pairs[:, 1]], a.image_shape, b.image_shape, c)
    cv2.setRNGSeed(0)
    plain = estimate_geometry(*args)
    cv2.setRNGSeed(0)
    counted = estimate_geometry(*args, log10_tests=0.5)
    assert plain.verified and counted.verified and counted.model == plain.model
    assert counted.nfa == pytest.approx(plain.nfa + 0.5) and counted.inliers == plain.inliers
    cv2.setRNGSeed(0)
    beyond = estimate_geometry(*args, log10_tests=c.max_log10_nfa - plain.nfa + 0.1)
    assert not beyond.verified and beyond.reason == "chance"


def test_the_upright_retry_runs_only_when_the_oriented_one_fails_and_counts_both_forms(kernels):
    a, b = _upright_pair()
    shapes = (a.image_shape, b.image_shape)

    def retry(q_desc, config=None, q_up=a.upright, p_up=b.upright):
        cv2.setRNGSeed(0)
        return verify_pair_bruteforce(a.keypoints, q_desc, shapes[0], b.keypoints, b.descriptors, shapes[1],
                                      config, q_upright=q_up, p_upright=p_up, distance="hamming")

    def alone(q_desc, p_desc):
        cv2.setRNGSeed(0)
        return verify_pair_bruteforce(a.keypoints, q_desc, shapes[0], b.keypoints, p_desc, shapes[1],
                                      VerificationConfig(), distance="hamming")

    oriented = alone(a.descriptors, b.descriptors)
    assert oriented.verified
    assert retry(a.descriptors).nfa == oriented.nfa  # passed: the upright form is not tried
    # Oriented descriptors that match nothing (another image's): the upright retry decides,
    # its NFA counting the two forms tried.
    other = FeatureExtractor(FeatureConfig("orb", 1000)).extract(texture(99)).descriptors[: len(a)]
    wrong = np.resize(other, a.descriptors.shape)
    assert not alone(wrong, b.descriptors).verified
    got = retry(wrong)
    upright = alone(a.upright, b.upright)
    assert got.verified and upright.verified
    assert got.nfa == pytest.approx(upright.nfa + UPRIGHT_LOG10_TESTS) and got.inliers == upright.inliers
    # Switched off, or a side without upright descriptors (a place stored before, another
    # robot's place): oriented matching alone.
    for result in (retry(wrong, VerificationConfig(upright=False)), retry(wrong, p_up=None), retry(wrong, q_up=None)):
        assert not result.verified


def test_fabmap_candidates_given_the_retry_skip_the_same_word_check_and_tracked_places_keep_it(tmp_path, monkeypatch):
    """CandidateConfig.retry_alone: FAB-MAP's first `bruteforce_fallback` candidates are checked
    by all-pairs matching alone; the candidates after them by same-word matching alone; the
    track's places by same-word matching, then the retry. False: every FAB-MAP candidate gets the
    same-word check first."""
    from aefabmap_runtime.core import detector as detector_module

    real, real_retry = detector_module.verify_pair, detector_module.verify_pair_bruteforce
    calls: list[tuple[str, bool]] = []

    def same_word_first(*args, bruteforce=False, **kw):
        calls.append(("same_word", bruteforce))
        return real(*args, bruteforce=bruteforce, **kw)

    def retry_alone(*args, **kw):
        calls.append(("retry", True))
        return real_retry(*args, **kw)

    monkeypatch.setattr(detector_module, "verify_pair", same_word_first)
    monkeypatch.setattr(detector_module, "verify_pair_bruteforce", retry_alone)
    seq = _skip_ahead_sequence()[:6] + [texture(98)]  # frame 6 is no revisit: every candidate fails
    for alone, want in ((True, [("retry", True), ("retry", True), ("same_word", False)]),
                        (False, [("same_word", True), ("same_word", True), ("same_word", False)])):
        calls.clear()
        _, r = _one_word_run(tmp_path / str(alone), seq, track=0, top_k=3, bruteforce_fallback=2, retry_alone=alone)
        assert not any(x.verified for x in r)
        assert r[6].candidates_tried == 3
        assert calls[-3:] == want
    # A revisit found by the retry alone is then followed along the track by same-word checks first.
    calls.clear()
    _, r = _one_word_run(tmp_path / "track", _revisit_sequence()[:8], track=2, track_memory=1, top_k=1)
    assert r[6].verified and r[6].verified_frame == 0 and r[7].verified and r[7].verified_frame == 1
    assert calls[-1] == ("same_word", True)
