"""ORB detected level by level on one pyramid (runtime/aefabmap_runtime/core/features/orb_levels.py):
cv2.ORB's own keypoints, by a cv2.ORB per level and by the compiled kernel, and cv2.ORB detects
where the level detector is not offered."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from aefabmap_runtime.core.features import features as F
from aefabmap_runtime.core.features.orb_description import pyramid
from aefabmap_runtime.core.features.orb_levels import (
    OrbLevelDetector,
    keypoint_rows,
    level_budgets,
    orientation_disc,
)
from aefabmap_runtime.core.kernels import native
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence


@pytest.fixture(scope="module")
def images():
    frames, _ = generate_loop_sequence(4, seed=3, size=(320, 240))
    rng = np.random.default_rng(2)
    noisy = [np.clip(f.astype(np.int16) + rng.integers(-40, 40, f.shape), 0, 255).astype(np.uint8) for f in frames]
    sizes = [(512, 410), (160, 120), (640, 64), (48, 40)]  # a detection image, a small frame, 10:1, tiny
    # black and white squares of 1-5 pixels: differences that saturate, scores at their extremes
    squares = [np.kron(rng.integers(0, 2, (480 // k, 640 // k)), np.ones((k, k))).astype(np.uint8) * 255
               for k in (1, 2, 3, 5)]
    flat = [np.full((240, 320), 128, np.uint8)]  # no corner
    return frames + noisy + [cv2.resize(noisy[0], s, interpolation=cv2.INTER_LINEAR) for s in sizes] + squares + flat


@pytest.fixture(params=[False, True], ids=["per-level-orb", "compiled"])
def compiled(request):
    if request.param and not native.available():
        pytest.skip("the compiled kernels are not built here")
    return request.param


def _rows(xy: np.ndarray, attrs: np.ndarray) -> np.ndarray:
    rows = np.column_stack([xy, attrs])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("settings", [{"nfeatures": 1000}, {"nfeatures": 300, "fastThreshold": 10},
                                      {"nfeatures": 2000, "nlevels": 5, "scaleFactor": 1.3},
                                      {"nfeatures": 500, "fastThreshold": 0, "patchSize": 21, "edgeThreshold": 21},
                                      {"nfeatures": 500, "fastThreshold": 60, "patchSize": 41, "edgeThreshold": 45}])
def test_level_by_level_detection_finds_orbs_own_keypoints(images, settings, compiled):
    orb = cv2.ORB_create(**settings)
    assert OrbLevelDetector.for_detector(orb) is not None
    detector = OrbLevelDetector(orb, compiled=compiled)
    assert detector.compiled == compiled
    for image in images:
        levels, _ = pyramid(image, orb.getNLevels(), orb.getScaleFactor())
        mine, theirs = _rows(*detector.detect(levels)), _rows(*keypoint_rows(orb.detect(image, None)))
        assert mine.shape == theirs.shape and np.array_equal(mine, theirs)


def test_each_level_keeps_orbs_share_of_the_budget(images):
    orb = cv2.ORB_create(nfeatures=1000)
    texture = cv2.resize(np.random.default_rng(5).integers(0, 256, (240, 320), np.uint8), (640, 480),
                         interpolation=cv2.INTER_LINEAR)  # corners everywhere: every level fills its share
    _, attrs = keypoint_rows(orb.detect(texture, None))
    counts = np.bincount(attrs[:, 3].astype(int), minlength=8)
    assert list(counts) == level_budgets(1000, 8, orb.getScaleFactor())
    assert sum(level_budgets(1000, 8, 1.2)) == 1000 and level_budgets(5, 8, 1.2)[-1] >= 0


def test_fasts_portable_form_finds_the_same_keypoints(images):
    # The portable form (GCC vectors) runs where AVX-512BW does not (ARM boards): the same keypoints.
    if not native.available():
        pytest.skip("the compiled kernels are not built here")
    orb = cv2.ORB_create(nfeatures=1000)
    detector = OrbLevelDetector(orb, compiled=True)
    for image in images:
        levels, _ = pyramid(image, orb.getNLevels(), orb.getScaleFactor())
        args = (levels, detector._crop, detector._edge, orb.getFastThreshold(), detector._budgets[: len(levels)],
                orb.getPatchSize() // 2, orientation_disc(orb.getPatchSize() // 2))
        fast, portable = native.orb_keypoints(*args), native.orb_keypoints(*args, portable=True)
        assert all(np.array_equal(a, b) for a, b in zip(fast, portable))


def test_the_compiled_detector_is_chosen_where_it_agrees():
    detector = OrbLevelDetector.for_detector(cv2.ORB_create(nfeatures=1000))
    assert detector.compiled == native.available()
    # FAST's score instead of Harris': the compiled kernel computes Harris' only
    fast_scored = OrbLevelDetector.for_detector(cv2.ORB_create(scoreType=cv2.ORB_FAST_SCORE))
    assert fast_scored is not None and not fast_scored.compiled
    # an edge threshold under half a patch: the orientation disc would leave the level
    assert not OrbLevelDetector(cv2.ORB_create(edgeThreshold=10, patchSize=31), compiled=True).compiled


def test_the_kernel_refuses_reads_outside_a_level():
    if not native.available():
        pytest.skip("the compiled kernels are not built here")
    levels = [np.zeros((64, 64), np.uint8)]
    disc = orientation_disc(15)
    with pytest.raises(ConfigError):
        native.orb_keypoints(levels, 0, 10, 20, [100], 15, disc)  # the disc reaches 15 pixels
    with pytest.raises(ConfigError):
        native.orb_keypoints(levels, 16, 3, 20, [100], 15, disc)  # the Harris window reaches 4
    bad = disc.copy()
    bad[3] = 40
    with pytest.raises(ConfigError):
        native.orb_keypoints(levels, 16, 15, 20, [100], 15, bad)


def test_orientation_disc_is_orbs():
    assert orientation_disc(15).tolist() == [15, 15, 15, 15, 14, 14, 14, 13, 13, 12, 11, 10, 9, 8, 6, 3]
    for half in (3, 10, 20):
        umax = orientation_disc(half)
        rows = [(v, u) for v in range(half + 1) for u in range(umax[v] + 1)]
        assert {(u, v) for v, u in rows} == set(rows)  # symmetric about the diagonal, as OpenCV makes it


def test_real_frames_get_orbs_own_keypoints(lip6):
    orb = cv2.ORB_create(nfeatures=1000)
    detector = OrbLevelDetector.for_detector(orb)
    for path in sorted(lip6.glob("*.jpg"))[::25]:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        image = cv2.resize(gray, (512, round(gray.shape[0] * 512 / gray.shape[1])), interpolation=cv2.INTER_LINEAR_EXACT)
        levels, _ = pyramid(image, orb.getNLevels(), orb.getScaleFactor())
        mine, theirs = _rows(*detector.detect(levels)), _rows(*keypoint_rows(orb.detect(image, None)))
        assert mine.shape == theirs.shape and np.array_equal(mine, theirs), path.name


def test_settings_it_does_not_cover_leave_detection_to_orb(images):
    assert OrbLevelDetector.for_detector(cv2.ORB_create(firstLevel=1)) is None
    assert OrbLevelDetector.for_detector(cv2.SIFT_create()) is None
    assert F.FeatureExtractor(F.FeatureConfig(kind="sift"))._levels is None


def test_the_extractor_gives_the_same_features_with_orbs_own_pyramid(images):
    config = F.FeatureConfig(max_features=1000, long_side=512, contrast_stretch=True)
    levels = F.FeatureExtractor(config, upright=True)
    own = F.FeatureExtractor(config, upright=True)
    own._levels = None
    assert levels._levels is not None
    for image in images:
        a, b = levels.extract(image), own.extract(image)
        for field in ("keypoints", "sizes", "descriptors", "upright"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), field
