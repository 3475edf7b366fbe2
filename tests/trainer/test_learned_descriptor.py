"""Training the learned ORB descriptor: keypoint pairs through a homography, the projection's
objective, and a bundle that carries it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_runtime.adapters.bundle_reader import load_bundle, load_detector
from aefabmap_runtime.core.features.features import FeatureConfig
from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES
from aefabmap_runtime.errors import ConfigError
from aefabmap_trainer import train as train_mod
from aefabmap_trainer import learned_descriptor
from aefabmap_trainer.learned_descriptor import WARPS, DescriptorTraining, _pairs, to_int8, train_projection
from aefabmap_trainer.match_pairs import random_homography
from aefabmap_trainer.train import TrainConfig, train_bundle


def test_pairs_are_mutual_nearest_within_the_radius_on_near_levels():
    h = np.array([[1.0, 0, 10], [0, 1, -5], [0, 0, 1]])
    ka = np.array([[50, 50], [100, 100], [200, 40], [300, 200]], np.float32)
    kb = np.array([[60.5, 45], [110, 95.2], [210, 35], [400, 10], [312, 195]], np.float32)
    la = np.array([0, 1, 0, 0], np.int32)
    lb = np.array([0, 3, 1, 0, 0], np.int32)
    ia, ib = _pairs(ka, la, kb, lb, h, scale=1.0)
    # a0 -> b0 (0.5 px); a1's partner is 2 levels away; a2 -> b2, one level up; a3 -> b4 (2 px).
    assert ia.tolist() == [0, 2, 3] and ib.tolist() == [0, 2, 4]
    # The radius is in detection pixels: at 2 detection pixels per image pixel, a3's 2 px are 4.
    ia, ib = _pairs(ka, la, kb, lb, h, scale=2.0)
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 2]


def test_the_projection_learns_what_stays_under_noise_and_light():
    rng = np.random.default_rng(0)
    n = 4096
    a = rng.integers(0, 256, (n, SAMPLES)).astype(np.float64)
    # The same patches darker, lower in contrast and noisy.
    b = np.clip(0.4 * a + 20 + rng.normal(0, 12, a.shape), 0, 255)
    a, b = a.astype(np.uint8), b.astype(np.uint8)
    learned = train_projection(a[:3072], b[:3072], DescriptorTraining(epochs=3, batch=256), show_progress=False)
    assert learned.weights.shape == (BITS, SAMPLES) and learned.weights.dtype == np.int8
    da, db = learned.bits(a[3072:]), learned.bits(b[3072:])
    pop = np.unpackbits(np.bitwise_xor(da, db), axis=1).sum(axis=1)
    other = np.unpackbits(np.bitwise_xor(da, np.roll(db, 1, axis=0)), axis=1).sum(axis=1)
    assert np.median(pop) < 0.2 * BITS and np.median(other) > 0.4 * BITS
    with pytest.raises(ConfigError):
        train_projection(a[:100], b[:100], DescriptorTraining(batch=256), show_progress=False)


def test_int8_scaling_keeps_every_sign_and_row_peak():
    w = np.random.default_rng(1).normal(size=(BITS, SAMPLES))
    q = to_int8(w)
    assert (np.abs(q).max(axis=1) == 127).all() and (np.sign(q)[np.abs(q) > 0] == np.sign(w)[np.abs(q) > 0]).all()


@pytest.mark.parametrize("bad", [dict(images=0), dict(epochs=0), dict(epochs=101), dict(batch=8), dict(warp="sideways")])
def test_bad_training_settings_are_refused(bad):
    with pytest.raises(ConfigError):
        DescriptorTraining(**bad)


@pytest.mark.parametrize("warp", sorted(WARPS))
def test_the_pairs_are_seen_through_the_chosen_warps_range(warp, image_dir, monkeypatch):
    seen = []

    def recorded(shape_hw, rng, **ranges):
        seen.append(ranges)
        return random_homography(shape_hw, rng, **ranges)

    monkeypatch.setattr(learned_descriptor, "random_homography", recorded)
    a, b = learned_descriptor.corresponding_patches(train_mod.find_training_images((image_dir,)), FeatureConfig("orb", 200),
                                                    DescriptorTraining(images=3, warp=warp), show_progress=False)
    assert seen and all(r == WARPS[warp] for r in seen) and len(a) == len(b) > 0


def test_the_residual_warps_stay_within_half_a_pyramid_step():
    rng = np.random.default_rng(0)
    centre = np.array([[[160.0, 120.0]]])
    for _ in range(200):
        h = random_homography((240, 320), rng, **WARPS["residual"])
        # the local scale at the centre: the root of the Jacobian's determinant, by finite differences
        p = [cv2.perspectiveTransform(centre + d, h)[0, 0] for d in ([[[0, 0]]], [[[1, 0]]], [[[0, 1]]])]
        scale = abs(np.linalg.det(np.column_stack([p[1] - p[0], p[2] - p[0]]))) ** 0.5
        assert 1 / 1.2 < scale < 1.2


def test_a_learned_bundle_is_trained_cached_and_runs(image_dir, tmp_path):
    features = FeatureConfig("orb", 200, descriptor="learned")
    cfg = TrainConfig(images=(image_dir,), out=tmp_path / "ld", features=features, words=32, max_descriptors=2000,
                      show_progress=False, cache_dir=tmp_path / "cache",
                      descriptor_training=DescriptorTraining(images=16, epochs=1, batch=32))
    result = train_bundle(cfg)
    b = load_bundle(result.path)
    assert b.features.descriptor == "learned" and b.learned_description is not None
    assert result.summary["descriptor_pairs"] >= 64 and "descriptor_s" in result.timings_s
    assert result.summary["descriptor_warp"] == "residual"
    # The vocabulary's words come from the learned bits: the cache entry is keyed by the projection.
    entries = list((tmp_path / "cache").glob("features-orb-*.npz"))
    assert len(entries) == 1
    brief = train_mod.cache_entry(tmp_path / "cache", "features", features, train_mod.find_training_images((image_dir,)))
    assert entries[0] != brief
    det = load_detector(result.path)
    import cv2

    for frame in sorted(image_dir.glob("frame_*.jpg"))[:4]:
        det.process(cv2.imread(str(frame)))
    with pytest.raises(ConfigError):
        TrainConfig(images=(image_dir,), out=tmp_path / "x", features=features, quantizer="ae")
