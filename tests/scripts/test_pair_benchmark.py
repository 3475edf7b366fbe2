"""scripts/pair_benchmark.py: the synthetic warps, the front-ends and the command on a tiny data tree."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import make_learned_bundle

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import pair_benchmark as pb  # noqa: E402


def texture(shape_hw=(360, 480), seed=0) -> np.ndarray:
    """A smooth random grayscale texture (blurred noise, stretched to 0-255) with corners to detect."""
    noise = np.random.default_rng(seed).random((shape_hw[0] // 4, shape_hw[1] // 4)).astype(np.float32)
    big = cv2.resize(noise, shape_hw[::-1], interpolation=cv2.INTER_CUBIC)
    return cv2.normalize(cv2.GaussianBlur(big, (0, 0), 1.5), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def test_rotation_homography_is_identity_at_zero_and_keeps_the_centre():
    shape = (120, 160)
    assert np.allclose(pb.rotation_homography(shape, 0), np.eye(3))
    H = pb.rotation_homography(shape, 30)
    centre = np.array([79.5, 59.5, 1.0])
    assert np.allclose((H @ centre) / (H @ centre)[2], centre)
    # Foreshortening: the side turned away shrinks, the vertical through the centre stays vertical.
    top, bottom = H @ [79.5, 0, 1], H @ [79.5, 119, 1]
    assert np.isclose(top[0] / top[2], bottom[0] / bottom[2])
    left = [H @ [0, y, 1] for y in (0, 119)]
    right = [H @ [159, y, 1] for y in (0, 119)]
    height = lambda pts: abs(pts[1][1] / pts[1][2] - pts[0][1] / pts[0][2])  # noqa: E731
    assert height(left) != pytest.approx(height(right), rel=0.05)


def test_scale_about_centre_keeps_the_size_and_pads_or_crops():
    gray = np.full((120, 160), 200, np.uint8)
    half = pb.scale_about_centre(gray, 0.5)
    assert half.shape == gray.shape
    assert half[0, 0] == 0 and half[60, 80] == 200 and (half > 0).sum() == 60 * 80
    doubled = pb.scale_about_centre(texture((120, 160)), 2.0)
    assert doubled.shape == (120, 160) and doubled.min() >= 0


def test_shrink_only_downsizes():
    gray = np.zeros((360, 480), np.uint8)
    assert pb.shrink(gray, 160).shape == (120, 160)
    assert pb.shrink(gray, 640) is gray and pb.shrink(gray, None) is gray


def test_learned_descriptors_are_skipped_without_contrib(monkeypatch):
    monkeypatch.delattr(cv2, "xfeatures2d", raising=False)
    with pytest.raises(pb.Unavailable, match="xfeatures2d"):
        pb.make_front_end("orb-teblid")
    with pytest.raises(ValueError):
        pb.make_front_end("surf")


@pytest.mark.parametrize("name", pb.FRONT_ENDS)
def test_front_end_verifies_a_warp_and_rejects_an_unrelated_image(name):
    try:
        front = pb.make_front_end(name)
    except pb.Unavailable as exc:
        pytest.skip(str(exc))
    config = pb.V.VerificationConfig()
    base = texture(seed=1)
    fa = front.extractor.extract(base)
    assert pb.verify(fa, front.extractor.extract(pb.rotate_view(base, 20)), front, config).verified
    assert not pb.verify(fa, front.extractor.extract(texture(seed=2)), front, config).verified


def test_command_on_a_tiny_training_tree(tmp_path):
    """Two CamVid drives of 12 frames (shifted crops of one texture each) and 6 Scene-15 images."""
    train = tmp_path / "train"
    for d, drive in enumerate(("0001TP", "0006R0")):
        world = texture((360, 720), seed=10 + d)
        (train / "camvid").mkdir(parents=True, exist_ok=True)
        for k in range(12):
            cv2.imwrite(str(train / "camvid" / f"{drive}_{k:06d}.jpg"), world[:, 8 * k:8 * k + 480])
    (train / "scene15" / "street").mkdir(parents=True)
    for k in range(6):
        cv2.imwrite(str(train / "scene15" / "street" / f"image_{k:04d}.jpg"), texture((200, 240), seed=20 + k))
    out = tmp_path / "pairs.json"
    pb.main(["orb", "--data", str(tmp_path), "--per-drive", "1", "--warps-per-setting", "2", "--long-side", "320",
             "--json", str(out)])
    result = json.loads(out.read_text())["results"]["orb"]
    assert set(result["gap"]) == {str(g) for g in pb.GAPS}
    assert set(result["angle"]) == {str(a) for a in pb.ANGLES} and set(result["scale"]) == {str(s) for s in pb.SCALES}
    assert result["negatives"] == 2 * 2 + 3 and result["negatives_accepted"] == 0
    assert result["gap"]["1"] == 100.0 and result["extract_ms"] > 0
    assert "| orb | 100% |" in pb.table({"orb": result})


def test_night_darkens_the_second_view_the_same_way_every_time(tmp_path):
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), texture((120, 160), seed=3))
    day = pb.render(pb.View(path), None)
    night = pb.render(pb.View(path, night=True), None)
    assert night.shape == day.shape and night.mean() < 0.5 * day.mean()
    assert np.array_equal(night, pb.render(pb.View(path, night=True), None))
    turned = pb.render(pb.View(path, ("rotate", 20), night=True), None)
    assert not np.array_equal(turned, pb.rotate_view(day, 20)) and turned.mean() < 0.5 * day.mean()


def test_night_pairs_keep_the_first_view_by_day(tmp_path):
    train = tmp_path / "train"
    for d, drive in enumerate(("0001TP", "0006R0")):
        (train / "camvid").mkdir(parents=True, exist_ok=True)
        for k in range(12):
            cv2.imwrite(str(train / "camvid" / f"{drive}_{k:06d}.jpg"), texture((60, 80), seed=30 + 12 * d + k))
    (train / "scene15" / "street").mkdir(parents=True)
    for k in range(4):
        cv2.imwrite(str(train / "scene15" / "street" / f"image_{k:04d}.jpg"), texture((60, 80), seed=60 + k))
    day = pb.benchmark_pairs(train, 0, 1, 2)
    night = pb.benchmark_pairs(train, 0, 1, 2, night=True)
    assert [(g, s, a, b.path, b.warp) for g, s, a, b in day] == [(g, s, a, b.path, b.warp) for g, s, a, b in night]
    assert not any(a.night for _, _, a, _ in night) and all(b.night for _, _, _, b in night)


def test_orb_learned_describes_with_the_bundles_projection(tmp_path):
    from aefabmap_runtime.core.features.features import FeatureConfig

    bundle, learned = make_learned_bundle(tmp_path / "b", FeatureConfig(descriptor="learned"), vocabulary_size=32)
    with pytest.raises(pb.Unavailable, match="--learned"):
        pb.make_front_end("orb-learned")
    front = pb.make_front_end("orb-learned", bundle)
    assert np.array_equal(front.extractor.learned.weights, learned.weights)
    base = texture(seed=1)
    fa = front.extractor.extract(base)
    # Random projections of the centred patch keep similar patches close (sign random projections).
    assert pb.verify(fa, front.extractor.extract(pb.rotate_view(base, 20)), front, pb.V.VerificationConfig()).verified
