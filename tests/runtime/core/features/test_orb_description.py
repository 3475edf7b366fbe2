"""ORB description by the compiled kernel (runtime/aefabmap_runtime/core/features/orb_description.py):
OpenCV's bytes, oriented and upright, from one blurred pyramid; OpenCV describes when it cannot."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_runtime.core.features import features as F
from aefabmap_runtime.core.features.orb_description import (
    PAIRS,
    OrbDescriber,
    compiled_resize_agrees,
    probe_pattern,
    pyramid,
)
from aefabmap_runtime.core.kernels import native
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

pytestmark = pytest.mark.skipif(not native.available(), reason="the compiled kernels are not built here")


@pytest.fixture(scope="module")
def frames():
    images, _ = generate_loop_sequence(8, seed=7, size=(320, 240))
    rng = np.random.default_rng(1)
    noisy = [np.clip(im.astype(np.int16) + rng.integers(-40, 40, im.shape), 0, 255).astype(np.uint8) for im in images]
    return images + noisy


def _opencv_features(config: F.FeatureConfig, image: np.ndarray) -> F.Features:
    extractor = F.FeatureExtractor(config, upright=True)
    extractor._describer = None  # OpenCV's detectAndCompute and compute, as before the kernel
    return extractor.extract(image)


@pytest.mark.parametrize("config", [F.FeatureConfig(max_features=1000, contrast_stretch=True),
                                    F.FeatureConfig(max_features=500, long_side=None),
                                    F.FeatureConfig(max_features=300, bucket_grid=4)])
def test_the_kernel_gives_opencvs_descriptors_oriented_and_upright(frames, config):
    extractor = F.FeatureExtractor(config, upright=True)
    assert extractor._describer is not None
    for image in frames:
        mine, theirs = extractor.extract(image), _opencv_features(config, image)
        assert len(mine) > 50
        for field in ("keypoints", "sizes", "descriptors", "upright"):
            a, b = getattr(mine, field), getattr(theirs, field)
            assert a.dtype == b.dtype and np.array_equal(a, b), field


def test_the_probed_pattern_is_orbs_and_stays_inside_the_patch():
    pattern = probe_pattern(cv2.ORB_create())
    assert pattern is not None and pattern.shape == (PAIRS, 4) and pattern.dtype == np.int32
    assert np.abs(pattern).max() <= 15
    assert not np.any((pattern[:, 0] == pattern[:, 2]) & (pattern[:, 1] == pattern[:, 3]))  # two points per test


def test_settings_it_does_not_cover_leave_description_to_opencv():
    assert OrbDescriber.for_detector(cv2.ORB_create(patchSize=21, edgeThreshold=21)) is None
    assert OrbDescriber.for_detector(cv2.ORB_create(WTA_K=3)) is None
    assert OrbDescriber.for_detector(cv2.SIFT_create()) is None
    assert F.FeatureExtractor(F.FeatureConfig(kind="sift"))._describer is None


def test_without_the_compiled_kernels_opencv_describes_the_same_bytes(frames, monkeypatch):
    config = F.FeatureConfig(max_features=400)
    expected = F.FeatureExtractor(config, upright=True).extract(frames[0])
    monkeypatch.setattr(native, "available", lambda: False)
    fallback = F.FeatureExtractor(config, upright=True)
    assert fallback._describer is None
    got = fallback.extract(frames[0])
    assert np.array_equal(got.descriptors, expected.descriptors) and np.array_equal(got.upright, expected.upright)


def test_a_keypoint_out_of_the_pyramids_reach_is_described_by_opencv(frames):
    extractor = F.FeatureExtractor(F.FeatureConfig(max_features=200), upright=True)
    work = frames[0]
    xy = np.array([[2.0, 2.0]], np.float32)  # the patch would leave the image
    assert extractor._describer.describe(work, xy, np.zeros(1, np.float32), np.zeros(1, np.int32)) is None
    assert extractor._describer.describe(work, xy, np.zeros(1, np.float32), np.array([9], np.int32)) is None


def test_the_kernel_refuses_arguments_that_do_not_agree():
    level = np.zeros((64, 64), np.uint8)
    pattern = np.zeros((PAIRS, 4), np.int32)
    one = np.zeros(1, np.float32)
    with pytest.raises(ConfigError):
        native.orb_describe([level], np.ones(1, np.float32), one, one, one, np.zeros(1, np.int32),
                            np.zeros((7, 4), np.int32), None, None)
    with pytest.raises(ConfigError):
        native.orb_describe([level], np.ones(1, np.float32), one, one, one, np.array([3], np.int32), pattern,
                            np.zeros((1, PAIRS // 8), np.uint8), None)
    with pytest.raises(ConfigError):
        native.orb_describe([level], np.ones(1, np.float32), one, one, one, np.zeros(1, np.int32), pattern,
                            np.zeros((2, PAIRS // 8), np.uint8), None)


def test_the_compiled_pyramid_gives_opencvs_levels():
    rng = np.random.default_rng(7)
    assert compiled_resize_agrees()
    for _ in range(150):
        rows, cols = (int(v) for v in rng.integers(1, 260, 2))
        smooth = cv2.resize(rng.integers(0, 256, (max(1, rows // 6), max(1, cols // 6)), dtype=np.uint8), (cols, rows))
        image = smooth if rng.random() < 0.5 else rng.integers(0, 256, (rows, cols), dtype=np.uint8)
        n_levels, factor = int(rng.integers(2, 10)), float(rng.uniform(1.01, 3.0))
        mine, inv = pyramid(image, n_levels, factor, compiled=True)
        theirs, inv_cv = pyramid(image, n_levels, factor, compiled=False)
        assert len(mine) == len(theirs) and np.array_equal(inv, inv_cv)
        assert all(np.array_equal(a, b) for a, b in zip(mine, theirs)), (rows, cols, n_levels, factor)


def test_the_compiled_pyramid_reads_strided_rows_and_one_pixel_images(frames):
    view = frames[0][7:200, 3:300]  # rows strided: a crop of a larger image
    mine, _ = pyramid(view, 8, 1.2, compiled=True)
    theirs, _ = pyramid(view, 8, 1.2, compiled=False)
    assert all(np.array_equal(a, b) for a, b in zip(mine, theirs))
    single = np.full((1, 1), 9, np.uint8)
    mine, _ = pyramid(single, 8, 1.2, compiled=True)
    theirs, _ = pyramid(single, 8, 1.2, compiled=False)
    assert [lv.tolist() for lv in mine] == [lv.tolist() for lv in theirs] == [[[9]]] * len(theirs)


def test_the_pyramid_kernel_refuses_levels_it_cannot_write():
    source = np.zeros((20, 20), np.uint8)
    read_only = np.zeros((10, 10), np.uint8)
    read_only.flags.writeable = False
    with pytest.raises(ConfigError):
        native.resize_levels([source, read_only])
    with pytest.raises(ConfigError):
        native.resize_levels([source, np.zeros((0, 10), np.uint8)])
    with pytest.raises(ConfigError):
        native.resize_levels([source, np.zeros((10, 10), np.float32)])
