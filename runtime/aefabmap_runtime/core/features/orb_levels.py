"""ORB's keypoints detected level by level on a pyramid built once (the one the descriptors use).

cv2.ORB's `detect` builds its own image pyramid, then detects on each level independently: FAST,
the strongest by FAST score, Harris responses, the strongest of those, orientations; each level
keeps its own share of the keypoint budget. The describer (`orb_description.py`) needs the same
pyramid, so building it twice cost a frame a second set of resizes. Here the pyramid is built
once and each level goes to a one-level cv2.ORB holding that level's share: the same keypoints,
responses and angles as OpenCV's own multi-level detection, which `OrbLevelDetector.for_detector`
checks on test images before it is used (else the extractor lets cv2.ORB detect).

ORB drops the keypoints within `edgeThreshold` pixels of a level's edge, after FAST has searched
the whole level. What a kept keypoint's tests read lies within half a patch of it (the orientation's
disc; FAST's circle and the Harris window are smaller), so each level is searched without its outer
edgeThreshold - patchSize / 2 pixels, by a cv2.ORB that drops keypoints within half a patch of
that crop's edge: the same keypoints, for less of FAST.

Where the compiled kernels are built, one call of `native.orb_keypoints` does the same for every
level (FAST, Harris responses, orientations: kernels.c), without a cv2.KeyPoint per keypoint; it is
used only when it gives cv2.ORB's keypoints on the test images here, as the per-level cv2.ORB is.
"""

from __future__ import annotations

import functools
import operator

import cv2
import numpy as np

from aefabmap_runtime.core.features.orb_description import level_scales, pyramid
from aefabmap_runtime.core.kernels import native


def level_budgets(n_features: int, n_levels: int, scale_factor: float) -> list[int]:
    """Keypoints each level keeps, as cv2.ORB shares them: a geometric series of ratio
    1 / scale_factor summing to n_features (float32 arithmetic, each level rounded, the last
    level taking what is left)."""
    factor = np.float32(1.0 / scale_factor)
    share = np.float32(n_features * (1 - factor) / (1 - np.float32(np.power(np.float64(factor), n_levels))))
    budgets = []
    for _ in range(n_levels - 1):
        budgets.append(int(np.rint(share)))
        share = np.float32(share * factor)
    budgets.append(max(n_features - sum(budgets), 0))
    return budgets


class OrbLevelDetector:
    """`orb`'s keypoints from a pyramid built by `orb_description.pyramid` (see module doc).

    compiled: detect with the compiled kernel (`native.orb_keypoints`, Harris score only) rather
    than a one-level cv2.ORB per level."""

    def __init__(self, orb, compiled: bool = False) -> None:
        n_levels, scale_factor = orb.getNLevels(), orb.getScaleFactor()
        self.n_levels, self.scale_factor = n_levels, scale_factor
        self.patch_size = orb.getPatchSize()
        self._scales = level_scales(n_levels, scale_factor)
        #: Pixels left out at each edge of a level (module doc), and the crop's own edge threshold.
        self._crop = max(0, orb.getEdgeThreshold() - orb.getPatchSize() // 2)
        self._edge = orb.getEdgeThreshold() - self._crop
        self._budgets = level_budgets(orb.getMaxFeatures(), n_levels, scale_factor)
        self._threshold = orb.getFastThreshold()
        # The kernel reads a keypoint's orientation disc and Harris window inside its level only.
        self.compiled = (bool(compiled) and native.available() and orb.getScoreType() == cv2.ORB_HARRIS_SCORE
                         and orb.getEdgeThreshold() >= max(4, self.patch_size // 2))
        self._disc = orientation_disc(self.patch_size // 2)
        self._levels = [] if self.compiled else [
            cv2.ORB_create(nfeatures=budget, scaleFactor=scale_factor, nlevels=1, edgeThreshold=self._edge,
                           firstLevel=0, WTA_K=orb.getWTA_K(), scoreType=orb.getScoreType(),
                           patchSize=orb.getPatchSize(), fastThreshold=self._threshold)
            for budget in self._budgets
        ]

    @classmethod
    def for_detector(cls, orb) -> OrbLevelDetector | None:
        """A level detector giving `orb`'s own keypoints, or None when it does not on the test
        images here (another OpenCV, other settings): the compiled kernel where it does, else a
        cv2.ORB per level."""
        if not isinstance(orb, cv2.ORB) or orb.getFirstLevel() != 0:
            return None
        settings = (orb.getMaxFeatures(), orb.getNLevels(), orb.getScaleFactor(), orb.getEdgeThreshold(),
                    orb.getFastThreshold(), orb.getScoreType(), orb.getPatchSize())
        for compiled in (True, False):
            if _agrees(*settings, compiled=compiled):
                return cls(orb, compiled=compiled)
        return None

    def detect(self, levels: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints of the pyramid `levels` (level 0 first): xy (N, 2) float32 in level-0 pixels
        and (N, 4) float32 rows (response, size, angle, octave), level by level."""
        if self.compiled:
            x, y, response, angle, level = native.orb_keypoints(
                levels, self._crop, self._edge, self._threshold, self._budgets[: len(levels)], self.patch_size // 2,
                self._disc)
        else:
            x, y, response, angle, level = self._detect_per_level(levels)
        # Scaled as ORB scales a level's coordinates: by the level's float32 scale, in float32; the
        # size is ORB's patch size times the level's scale.
        scale = self._scales[level]
        xy = np.column_stack([x.astype(np.float32) * scale, y.astype(np.float32) * scale])
        attrs = np.column_stack([response, np.float32(self.patch_size) * scale, angle, level.astype(np.float32)])
        return xy, attrs.astype(np.float32, copy=False)

    def _detect_per_level(self, levels: list[np.ndarray]) -> tuple[np.ndarray, ...]:
        """`native.orb_keypoints`' arrays, by a one-level cv2.ORB on each level's crop: x, y
        (float32 level pixels), response, angle and level."""
        found = []
        crop = self._crop
        for level, (orb, image) in enumerate(zip(self._levels, levels)):
            if min(image.shape) <= 2 * crop:
                continue  # no pixel lies edgeThreshold away from every edge: ORB keeps none
            kps = orb.detect(image[crop: image.shape[0] - crop, crop: image.shape[1] - crop], None)
            if not kps:
                continue
            # Back to the level's pixels (whole numbers: exact).
            at = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32, copy=False) + np.float32(crop)
            found.append((at[:, 0], at[:, 1], _attribute(kps, "response"), _attribute(kps, "angle"),
                          np.full(len(kps), level, np.int32)))
        if not found:
            return (np.zeros(0, np.float32),) * 4 + (np.zeros(0, np.int32),)
        return tuple(np.concatenate(column) for column in zip(*found))


def orientation_disc(half_patch: int) -> np.ndarray:
    """(half_patch + 1,) int32: the half-width of each row of ORB's orientation disc of radius
    half_patch, as OpenCV's ORB computes it (rows 0 .. half_patch; made symmetric about the
    diagonal)."""
    umax = [0] * (half_patch + 2)
    vmax = int(np.floor(half_patch * np.sqrt(np.float32(2)) / 2 + 1))
    vmin = int(np.ceil(half_patch * np.sqrt(np.float32(2)) / 2))
    for v in range(vmax + 1):
        umax[v] = int(np.rint(half_patch * np.sqrt(1 - v * v / float(half_patch * half_patch))))
    v0 = 0
    for v in range(half_patch, vmin - 1, -1):
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    return np.array(umax[: half_patch + 1], np.int32)


def keypoint_rows(kps) -> tuple[np.ndarray, np.ndarray]:
    """cv2.KeyPoints as `OrbLevelDetector.detect` returns them: xy (N, 2), (N, 4) rows of
    (response, size, angle, octave), float32."""
    if not len(kps):
        return np.zeros((0, 2), np.float32), np.zeros((0, 4), np.float32)
    xy = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32, copy=False)
    attrs = np.column_stack([_attribute(kps, name) for name in ("response", "size", "angle", "octave")])
    return xy, attrs


def _attribute(kps, name: str) -> np.ndarray:
    """(N,) float32 of one attribute of every cv2.KeyPoint, one attribute per pass (numpy's
    fromiter over tuples of several cost several times more per keypoint)."""
    return np.fromiter(map(operator.attrgetter(name), kps), np.float32, len(kps))


@functools.lru_cache(maxsize=16)
def _agrees(n_features, n_levels, scale_factor, edge_threshold, fast_threshold, score_type, patch_size,
            compiled: bool) -> bool:
    """Whether the level detector (compiled or not) finds cv2.ORB's keypoints (positions,
    responses, sizes, angles, octaves), on seeded textured test images of two sizes; once per
    process and setting (every thread's extractor asks)."""
    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=scale_factor, nlevels=n_levels,
                         edgeThreshold=edge_threshold, fastThreshold=fast_threshold, scoreType=score_type,
                         patchSize=patch_size)
    mine = OrbLevelDetector(orb, compiled=compiled)
    if mine.compiled != compiled:
        return False
    rng = np.random.default_rng(0)
    for size in ((512, 384), (333, 250)):
        image = cv2.resize(rng.integers(0, 256, (size[1] // 4, size[0] // 4), dtype=np.uint8), size,
                           interpolation=cv2.INTER_LINEAR)
        levels, _ = pyramid(image, n_levels, scale_factor)
        xy, attrs = mine.detect(levels)
        ref_xy, ref_attrs = keypoint_rows(orb.detect(image, None))
        if len(ref_xy) < 50:
            return False
        ours = np.column_stack([xy, attrs])
        theirs = np.column_stack([ref_xy, ref_attrs])
        if ours.shape != theirs.shape or not np.array_equal(ours[np.lexsort(ours.T[::-1])],
                                                           theirs[np.lexsort(theirs.T[::-1])]):
            return False
    return True
