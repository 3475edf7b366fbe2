"""scripts/descriptor_forms_benchmark.py: every compiled form timed on the same keypoints, bytes checked."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES, LearnedDescription
from aefabmap_runtime.core.kernels import native

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import descriptor_forms_benchmark as dfb  # noqa: E402


def texture(seed: int = 0) -> np.ndarray:
    small = np.random.default_rng(seed).integers(0, 256, (60, 80), dtype=np.uint8)
    return cv2.resize(small, (640, 480), interpolation=cv2.INTER_CUBIC)


def test_frames_are_scaled_to_the_long_side_and_keep_orbs_keypoints():
    levels, inv, xy, angle, octave = dfb.prepared(texture())
    assert max(levels[0].shape) == dfb.LONG_SIDE and inv[0] == 1.0
    assert 0 < len(xy) <= dfb.KEYPOINTS and xy.shape == (len(angle), 2) == (len(octave), 2)
    assert octave.min() >= 0 and octave.max() < len(levels)


@pytest.mark.skipif(not native.available(), reason="the compiled kernels are not built here")
def test_every_form_is_timed_and_gives_numpys_bytes():
    weights = np.random.default_rng(1).integers(-128, 128, (BITS, SAMPLES)).astype(np.int8)
    result = dfb.time_forms(LearnedDescription(weights), [dfb.prepared(texture(s)) for s in (2, 3)], repeats=1)
    assert list(result["forms"]) == list(native.LEARNED_FORMS) and result["keypoints"] > 0
    for figures in result["forms"].values():
        assert figures["same_bytes_as_numpy"] and figures["ms_per_1000_keypoints"] >= 0


def test_a_missing_bundle_is_one_line_and_a_failure(tmp_path, capsys):
    assert dfb.main(["--model", str(tmp_path / "missing"), "--images", str(tmp_path)]) == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
