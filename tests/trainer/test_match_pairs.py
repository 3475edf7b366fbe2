"""Matching pairs for the AE's matching term: synthetic warps and consecutive frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
from aefabmap_trainer.match_pairs import (
    MatchPairs,
    build_match_pairs,
    consecutive_frames,
    project,
    random_homography,
    ratio_matches,
    warp_pairs,
)


def textured_image(seed: int = 0, shape=(360, 480)) -> np.ndarray:
    """Random rectangles and circles on a noisy background: plenty of distinct corners."""
    rng = np.random.default_rng(seed)
    img = (rng.random(shape) * 40 + 100).astype(np.uint8)
    for _ in range(120):
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        c = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(8, 50)), y + int(rng.integers(8, 50))), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(4, 25)), c, -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_warp_pairs_are_true_correspondences(kind):
    img = textured_image()
    rng = np.random.default_rng(1)
    h = random_homography(img.shape, rng)
    warped = cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]))
    fx = FeatureExtractor(FeatureConfig(kind=kind, long_side=None))
    fa, fb = fx.extract(img), fx.extract(warped)
    idx = warp_pairs(fa, fb, h, tolerance_px=2.0)
    assert len(idx) >= 30
    err = np.linalg.norm(project(h, fa.keypoints[idx[:, 0]]) - fb.keypoints[idx[:, 1]], axis=1)
    assert err.max() <= 2.0
    assert len(set(idx[:, 0].tolist())) == len(idx) == len(set(idx[:, 1].tolist()))  # one-to-one
    # Descriptors of true correspondences are far more alike than random pairs.
    va, vb = fx.kind.vectors(fa.descriptors[idx[:, 0]]), fx.kind.vectors(fb.descriptors[idx[:, 1]])
    shuffled = vb[np.roll(np.arange(len(vb)), 1)]
    assert np.median(((va - vb) ** 2).sum(1)) < 0.6 * np.median(((va - shuffled) ** 2).sum(1))


def test_identity_warp_pairs_every_keypoint():
    img = textured_image(2)
    fx = FeatureExtractor(FeatureConfig(kind="orb", long_side=None))
    f = fx.extract(img)
    idx = warp_pairs(f, f, np.eye(3))
    assert np.array_equal(idx[:, 0], idx[:, 1]) and len(idx) >= len(f) * 0.95


def test_ratio_matches_agree_with_the_known_warp():
    img = textured_image(3)
    h = random_homography(img.shape, np.random.default_rng(4), max_angle_deg=5, max_perspective=0.05)
    warped = cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]))
    fx = FeatureExtractor(FeatureConfig(kind="orb", long_side=None))
    fa, fb = fx.extract(img), fx.extract(warped)
    idx = ratio_matches(fa, fb, "hamming")
    assert len(idx) >= 20
    err = np.linalg.norm(project(h, fa.keypoints[idx[:, 0]]) - fb.keypoints[idx[:, 1]], axis=1)
    assert np.mean(err < 4.0) > 0.9


def test_consecutive_frames_pairs_neighbours_of_one_drive():
    names = ["0001TP_006690.jpg", "0001TP_006720.jpg", "0001TP_009000.jpg", "0006R0_f00930.jpg",
             "0016E5_00390.jpg", "0016E5_00420.jpg", "bedroom_1.jpg"]
    pairs = consecutive_frames([Path(n) for n in names])
    assert [(a.name, b.name) for a, b in pairs] == [
        ("0001TP_006690.jpg", "0001TP_006720.jpg"), ("0016E5_00390.jpg", "0016E5_00420.jpg")]


def test_build_match_pairs_and_group_split(tmp_path):
    files = []
    for i in range(6):
        p = tmp_path / f"seq_{i * 30:05d}.png"
        cv2.imwrite(str(p), textured_image(10 + i))
        files.append(p)
    fx = FeatureExtractor(FeatureConfig(kind="orb", long_side=None))
    pairs = build_match_pairs(files, fx, warp_images=4, frame_pairs=0, seed=0)
    assert pairs.a.shape == pairs.b.shape and pairs.a.shape[1] == 256 and len(pairs) > 100
    assert set(np.unique(pairs.group).tolist()) == {0, 1, 2, 3}
    train, val = pairs.split(0.25, seed=0)
    assert len(train) + len(val) == len(pairs)
    assert not set(train.group.tolist()) & set(val.group.tolist())
    assert isinstance(train, MatchPairs)
