"""scripts/night_keypoints.py: day keypoints found again and matched under a synthetic night."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.core.features.features import Features
from aefabmap_trainer.multiview import is_test_image
from tests.conftest import make_synthetic_bundle, rectangles_image

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import night_keypoints as nk  # noqa: E402


def _features(xy, sizes) -> Features:
    return Features(np.asarray(xy, np.float32), np.asarray(sizes, np.float32), np.zeros((len(sizes), 32), np.uint8),
                    (100, 100))


def test_a_keypoint_repeats_on_its_own_level_within_two_of_its_pixels():
    day = _features([[10, 10], [50, 50], [80, 20]], [31.0, 62.0, 31.0])
    # level 1 (size 62): 2 of its pixels are 4 image pixels; level 0's partner is 2.5 px away
    night = _features([[13.9, 10], [50, 53.9], [80, 22.5], [10, 10.5]], [62.0, 62.0, 31.0, 31.0])
    assert nk.repeated_partner(day, night).tolist() == [3, 1, -1]


def test_a_match_counts_only_when_the_matcher_pairs_the_repeated_partner():
    partner = np.array([2, -1, 0, 1])
    pairs = np.array([[2, 0], [1, 1], [1, 2], [1, 3]])  # (night, day): day 0 right, 1 has none, 2 wrong
    assert nk.matched(partner, pairs).tolist() == [True, False, False, True]


def test_the_night_takes_more_keypoints_than_day_noise(tmp_path):
    camvid = tmp_path / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    candidates = [f"frame_{k:04d}.jpg" for k in range(200)]
    names = [n for n in candidates if is_test_image(Path(n))][:3]
    outside = next(n for n in candidates if not is_test_image(Path(n)))  # left out: a training image
    for k, name in enumerate([*names, outside]):
        cv2.imwrite(str(camvid / name), rectangles_image(k))
    assert nk.test_split(tmp_path / "data", 10) == sorted(camvid / n for n in names)

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    out = tmp_path / "night.json"
    assert nk.main(["--model", str(bundle), "--data", str(tmp_path / "data"), "--json", str(out), "--no-progress"]) == 0
    result = json.loads(out.read_text())["results"]
    assert set(result) == set(nk.CONDITIONS)
    for row in result.values():
        assert row["keypoints"] > 100
        assert row["matched_either"] <= row["repeated"] <= row["keypoints"]
        assert max(row["matched_oriented"], row["matched_upright"]) <= row["matched_either"]
    assert result["day noise"]["shares"]["repeated"] > 0.8
    assert result["night"]["shares"]["repeated"] < result["day noise"]["shares"]["repeated"] - 0.1
    # the same noise for the same seed
    again = nk.measure(load_detector(bundle), nk.test_split(tmp_path / "data", 10), {"night": nk.CONDITIONS["night"]},
                       show_progress=False)
    assert again["night"]["repeated"] == result["night"]["repeated"]


def test_a_folder_without_test_images_is_one_line_and_exit_1(tmp_path, capsys):
    bundle = make_synthetic_bundle(tmp_path / "bundle")
    assert nk.main(["--model", str(bundle), "--data", str(tmp_path / "nothing"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("night_keypoints: no test-split image") and "\n" not in err
