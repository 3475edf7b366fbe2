"""Feature-kind registry: built-in kinds, and a throwaway binary kind registered in one place."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap import BundleError, ConfigError, InputError
from aefabmap_runtime.adapters.bundle_reader import load_bundle, load_detector
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.features.feature_kinds import (
    BinaryKind,
    FloatKind,
    get_kind,
    kind_names,
    register,
    unregister,
)
from aefabmap_runtime.core.features.features import (
    FeatureConfig,
    FeatureExtractor,
    descriptor_vectors,
)
from aefabmap_runtime.core.map.keypoint_store import KeypointStore
from aefabmap_runtime.core.verify.verification import NO_WORD, VerificationConfig, match_keypoints
from tests.conftest import make_synthetic_bundle
from tests.runtime.core.verify.test_verification import PERSPECTIVE, texture

AKAZE = "akaze_test"


@pytest.fixture
def akaze():
    """AKAZE's 61-byte (488-bit) binary descriptor, registered for the test only."""
    kind = register(BinaryKind(AKAZE, 61, lambda n: cv2.AKAZE_create()))
    try:
        yield kind
    finally:
        unregister(AKAZE)


def test_builtin_kinds_declare_their_contract():
    orb, sift = get_kind("orb"), get_kind("sift")
    assert kind_names()[:2] == ("orb", "sift")
    assert (orb.width, orb.dtype, orb.distance, orb.vector_length, orb.store_bytes) == (32, np.uint8, "hamming", 256, 32)
    assert (sift.width, sift.dtype, sift.distance, sift.vector_length, sift.store_bytes) == (128, np.float32, "l2", 128, 128)
    assert (orb.ae_scaling, sift.ae_scaling) == ("none", "minmax")
    assert sift.options == ("rootsift",) and orb.options == ()
    assert FeatureConfig("orb").descriptor_length == 256 and FeatureConfig("sift").descriptor_length == 128


def test_registry_refuses_duplicates_unknown_names_and_builtin_removal(akaze):
    with pytest.raises(ConfigError):
        register(BinaryKind(AKAZE, 61, lambda n: cv2.AKAZE_create()))
    with pytest.raises(ConfigError):
        get_kind("surf")
    with pytest.raises(ConfigError):
        unregister("orb")
    with pytest.raises(ConfigError):
        BinaryKind("zero", 0, lambda n: None)
    with pytest.raises(ConfigError):
        FeatureConfig(AKAZE, rootsift=True)  # the kind declares no rootsift option


def test_a_kind_checks_its_descriptors():
    orb, sift = get_kind("orb"), get_kind("sift")
    with pytest.raises(InputError):
        orb.vectors(np.zeros((3, 32), np.float32))  # right width, wrong dtype: not guessed
    with pytest.raises(InputError):
        orb.vectors(np.zeros((3, 61), np.uint8))
    with pytest.raises(InputError):
        sift.vectors(np.zeros((3, 32), np.float32))
    d = np.random.default_rng(0).random((5, 128)).astype(np.float32)
    assert np.array_equal(sift.vectors(d), d) and sift.compress(d).max() == 255


def test_registered_binary_kind_extracts_quantises_and_matches_with_hamming(akaze):
    cfg = FeatureConfig(AKAZE, max_features=300, long_side=None)
    assert cfg.descriptor_length == 488
    feats = FeatureExtractor(cfg).extract(texture(1))
    assert 50 <= len(feats) <= 300 and feats.descriptors.shape == (len(feats), 61) and feats.descriptors.dtype == np.uint8
    # Declared vector form: the unpacked bits.
    vec = descriptor_vectors(feats.descriptors, AKAZE)
    assert vec.shape == (len(feats), 488) and np.array_equal(vec, np.unpackbits(feats.descriptors, axis=1))

    # Matching follows the kind's distance. A query row q and two place rows: `near_l2` flips
    # 8 bits of one byte (127 -> 128: L2-close, Hamming 8), `near_hamming` flips 3 bits of
    # another byte (0 -> 224: L2-far, Hamming 3). Hamming must pick near_hamming.
    q = np.full((1, 61), 0x55, np.uint8)
    q[0, 0], q[0, 1] = 127, 0
    near_l2, near_hamming = q.copy(), q.copy()
    near_l2[0, 0] = 128
    near_hamming[0, 1] = 224
    p = np.vstack([near_l2, near_hamming])
    words = np.zeros(1), np.zeros(2)
    loose = VerificationConfig(ratio=1.0)
    assert match_keypoints(words[0], q, words[1], p, loose, distance=akaze.distance).tolist() == [[0, 1]]
    assert match_keypoints(words[0], q, words[1], p, loose, distance="l2").tolist() == [[0, 0]]


def test_registered_binary_kind_runs_through_bundle_and_detector(akaze, tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "b", vocabulary_size=32, kind=AKAZE)
    assert load_bundle(bundle).descriptor_length == 488
    det = load_detector(bundle, DetectorConfig(exclude=0))
    assert det.store.bytes_per_keypoint == 4 + 2 + 61
    place = texture(1)
    query = cv2.warpPerspective(place, PERSPECTIVE, (place.shape[1], place.shape[0]))
    # Quantised in the declared vector form: nearest centroid of the unpacked bits.
    feats = det.extractor.extract(query)
    centroids = np.load(bundle / "vocabulary.npy")
    bits = np.unpackbits(feats.descriptors, axis=1).astype(np.float32)
    expect = np.argmin(((bits[:, None, :] - centroids[None]) ** 2).sum(axis=2), axis=1)
    budget = det.bundle.features.max_features  # beyond it: verification-only keypoints, no word
    words = det.words_of(feats)
    assert np.array_equal(words[:budget], expect[:budget]) and np.all(words[budget:] == NO_WORD)
    det.process(place)
    r = det.process(query)
    assert r.verified and r.verified_frame == 0 and r.inliers >= 15
    unregister(AKAZE)
    with pytest.raises(BundleError):
        load_bundle(bundle)  # a bundle of an unknown kind is refused, not guessed


def test_store_form_comes_from_the_kind():
    rng = np.random.default_rng(2)
    sift = get_kind("sift")
    d = rng.random((10, 128)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    store = KeypointStore(sift, vocabulary_size=100)
    place = store.pack(rng.uniform(0, 100, (10, 2)), np.arange(10), d, (100, 100))
    assert np.array_equal(place.descriptors, sift.compress(d)) and store.bytes_per_keypoint == 4 + 2 + 128
    custom = FloatKind("float_test", 16, lambda n: None)
    assert KeypointStore(custom, 100).bytes_per_keypoint == 4 + 2 + 16
