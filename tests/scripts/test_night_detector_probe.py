"""scripts/night_detector_probe.py: a small learned detector against ORB's at night."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_trainer.multiview import is_test_image
from tests.conftest import rectangles_image

pytest.importorskip("torch")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import night_detector_probe as probe  # noqa: E402


def _data(root: Path) -> Path:
    camvid = root / "data" / "train" / "camvid"
    camvid.mkdir(parents=True)
    names = [f"frame_{k:04d}.jpg" for k in range(200)]
    test = [n for n in names if is_test_image(Path(n))][:2]
    training = [n for n in names if not is_test_image(Path(n))][:4]
    for k, name in enumerate(test + training):
        cv2.imwrite(str(camvid / name), rectangles_image(k, (192, 256)))
    return root / "data"


def test_a_corner_repeats_within_two_pixels():
    day = np.array([[10, 10], [50, 50], [80, 20]], np.float32)
    other = np.array([[11.5, 10.5], [50, 53], [200, 200]], np.float32)
    assert probe.repeated(day, other).tolist() == [True, False, False]
    assert probe.repeated(day, np.zeros((0, 2), np.float32)).tolist() == [False] * 3


def test_stable_labels_keep_only_corners_the_nights_leave(tmp_path):
    cv2.imwrite(str(tmp_path / "frame.jpg"), rectangles_image(7, (192, 256)))
    gray = probe.load_level(tmp_path / "frame.jpg")
    every = probe.label_map(gray, 0, np.random.default_rng(0))
    stable = probe.label_map(gray, probe.LABEL_NIGHTS, np.random.default_rng(0))
    assert every.sum() > 50
    assert 0 < stable.sum() < every.sum()
    assert np.all(every[stable > 0] == 1)


def test_the_probe_trains_measures_and_times_a_net(tmp_path):
    out = tmp_path / "probe.json"
    assert probe.main(["--data", str(_data(tmp_path)), "--widths", "2,4,4", "--steps", "30", "--json", str(out),
                       "--threads", "1", "--no-progress"]) == 0
    result = json.loads(out.read_text())
    assert result["train_images"] == 4 and result["test_images"] == 2
    assert set(result["repeated"]) == set(probe.CONDITIONS)
    for row in result["repeated"].values():
        assert 0.0 <= row["orb"] <= 1.0 and 0.0 <= row["learned"] <= 1.0
    # ORB's own corners: the night takes some of what day noise leaves
    assert result["repeated"]["night"]["orb"] < result["repeated"]["day noise"]["orb"]
    assert result["cost_ms_one_level"]["float32"] > 0 and result["cost_ms_one_level"]["int8"] > 0
    assert result["level_hw"] == [384, 512]


def test_a_folder_without_images_or_bad_widths_is_one_line_and_exit_1(tmp_path, capsys):
    assert probe.main(["--data", str(tmp_path / "nothing"), "--no-progress"]) == 1
    assert probe.main(["--data", str(tmp_path), "--widths", "8,0,4", "--no-progress"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all(line.startswith("night_detector_probe: ") for line in lines)
