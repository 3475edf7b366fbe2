"""Matching descriptor pairs for the AE's matching term: the same scene point seen twice.

Two sources, both from training images only:
- synthetic warps: an image and a random homography warp of it; a keypoint pair is kept when
  the warped keypoint lies within `tolerance_px` of the projected original and the two are
  mutual nearest neighbours in position (ground truth by construction, no descriptor involved);
- consecutive frames of a drive (CamVid): brute-force descriptor matching with Lowe's ratio
  test and mutual check, then a RANSAC fundamental-matrix inlier check.

Pairs are returned as descriptor vectors (the kind's `vectors` form, what quantisers consume).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.features.features import FeatureExtractor, Features


def held_out_groups(group: np.ndarray, val_fraction: float, seed: int) -> np.ndarray:
    """(N,) bool: the rows whose group is among the val_fraction of groups drawn (seeded) for
    held-out use; none when there is a single group."""
    groups = np.unique(group)
    rng = np.random.default_rng(seed)
    n_val = max(1, int(round(val_fraction * groups.size))) if groups.size > 1 else 0
    val_groups = rng.choice(groups, size=n_val, replace=False) if n_val else np.zeros(0, group.dtype)
    return np.isin(group, val_groups)


@dataclass
class MatchPairs:
    """a, b: (P, D) float32 descriptor vectors of matched keypoints; group: (P,) int32 source index
    (image or frame pair), so a held-out split can keep whole groups apart."""

    a: np.ndarray
    b: np.ndarray
    group: np.ndarray

    def __len__(self) -> int:
        return int(self.a.shape[0])

    def split(self, val_fraction: float, seed: int) -> tuple["MatchPairs", "MatchPairs"]:
        """(train, val) split by whole groups (seeded)."""
        is_val = held_out_groups(self.group, val_fraction, seed)
        return self.subset(~is_val), self.subset(is_val)

    def subset(self, mask: np.ndarray) -> "MatchPairs":
        return MatchPairs(self.a[mask], self.b[mask], self.group[mask])

    @staticmethod
    def concat(parts: list["MatchPairs"], d: int) -> "MatchPairs":
        if not parts:
            return MatchPairs(np.zeros((0, d), np.float32), np.zeros((0, d), np.float32), np.zeros(0, np.int32))
        return MatchPairs(np.concatenate([p.a for p in parts]), np.concatenate([p.b for p in parts]),
                          np.concatenate([p.group for p in parts]).astype(np.int32))


def random_homography(shape_hw: tuple[int, int], rng: np.random.Generator, *, max_angle_deg: float = 20.0,
                      scale_range: tuple[float, float] = (0.75, 1.25), max_perspective: float = 0.15,
                      max_shift: float = 0.08) -> np.ndarray:
    """A random 3x3 homography for an image of shape (H, W): rotation, scale, shift about the centre
    and a corner jitter (max_perspective x side) that adds perspective; maps original -> warped px."""
    h, w = shape_hw
    cx, cy = w / 2.0, h / 2.0
    a = np.deg2rad(rng.uniform(-max_angle_deg, max_angle_deg))
    s = rng.uniform(*scale_range)
    sim = np.array([[s * np.cos(a), -s * np.sin(a), 0], [s * np.sin(a), s * np.cos(a), 0], [0, 0, 1]])
    to_c = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], float)
    back = np.array([[1, 0, cx + rng.uniform(-max_shift, max_shift) * w],
                     [0, 1, cy + rng.uniform(-max_shift, max_shift) * h], [0, 0, 1]], float)
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)
    moved = project(back @ sim @ to_c, corners)
    # Jitter the corners' images independently: adds perspective on top of the similarity.
    moved += rng.uniform(-max_perspective, max_perspective, (4, 2)) * [w, h] / 2
    return cv2.getPerspectiveTransform(corners.astype(np.float32), moved.astype(np.float32)).astype(np.float64)


def project(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (N, 2) mapped by homography h (3, 3) -> (N, 2)."""
    if pts.shape[0] == 0:
        return pts.reshape(0, 2).astype(np.float64)
    p = np.hstack([pts.astype(np.float64), np.ones((pts.shape[0], 1))]) @ h.T
    return p[:, :2] / p[:, 2:3]


def warp_pairs(fa: Features, fb: Features, h: np.ndarray, tolerance_px: float = 2.0) -> np.ndarray:
    """Index pairs (P, 2) of keypoints of fa and fb (fb extracted from the image warped by h) that
    are mutual nearest neighbours in position after projecting fa's keypoints, within tolerance_px."""
    if len(fa) == 0 or len(fb) == 0:
        return np.zeros((0, 2), np.int64)
    pa = project(h, fa.keypoints)
    d2 = ((pa[:, None, :] - fb.keypoints[None, :, :].astype(np.float64)) ** 2).sum(-1)  # (Na, Nb)
    nn_ab = d2.argmin(1)
    nn_ba = d2.argmin(0)
    ia = np.arange(len(fa))
    ok = (nn_ba[nn_ab] == ia) & (d2[ia, nn_ab] <= tolerance_px**2)
    return np.stack([ia[ok], nn_ab[ok]], axis=1)


def ratio_matches(fa: Features, fb: Features, distance: str, ratio: float = 0.8) -> np.ndarray:
    """Index pairs (P, 2): mutual brute-force matches passing Lowe's ratio test both ways,
    then RANSAC fundamental-matrix inliers (3 px) when at least 15 remain."""
    if len(fa) < 2 or len(fb) < 2:
        return np.zeros((0, 2), np.int64)
    norm = cv2.NORM_HAMMING if distance == "hamming" else cv2.NORM_L2
    bf = cv2.BFMatcher(norm)

    def one_way(x, y):
        best = {}
        for m in bf.knnMatch(x, y, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                best[m[0].queryIdx] = m[0].trainIdx
        return best

    ab, ba = one_way(fa.descriptors, fb.descriptors), one_way(fb.descriptors, fa.descriptors)
    pairs = np.array(sorted((i, j) for i, j in ab.items() if ba.get(j) == i), np.int64).reshape(-1, 2)
    if pairs.shape[0] >= 15:
        _, inl = cv2.findFundamentalMat(fa.keypoints[pairs[:, 0]], fb.keypoints[pairs[:, 1]], cv2.FM_RANSAC, 3.0, 0.99)
        if inl is None:
            return np.zeros((0, 2), np.int64)
        pairs = pairs[inl.ravel().astype(bool)]
    else:
        pairs = pairs[:0]
    return pairs


# CamVid file names: <sequence>_<frame number>.png/jpg, e.g. 0001TP_006690.jpg.
_CAMVID = re.compile(r"^(?P<seq>[^_]+)_(?P<frame>\d+)$")


def consecutive_frames(files: list[Path], max_gap: int = 60) -> list[tuple[Path, Path]]:
    """Pairs of neighbouring frames of the same drive (same prefix, frame numbers <= max_gap apart)."""
    parsed = []
    for f in files:
        m = _CAMVID.match(f.stem)
        if m:
            parsed.append((m["seq"], int(m["frame"]), f))
    parsed.sort(key=lambda t: (t[0], t[1]))
    return [(a[2], b[2]) for a, b in zip(parsed, parsed[1:]) if a[0] == b[0] and 0 < b[1] - a[1] <= max_gap]


def build_match_pairs(
    files: list[Path],
    extractor: FeatureExtractor,
    *,
    warp_images: int,
    frame_pairs: int,
    seed: int,
    load=None,
    progress: bool = False,
) -> MatchPairs:
    """Matching pairs from `warp_images` synthetic warps of (seeded) training images and up to
    `frame_pairs` consecutive-frame pairs of the drives among `files`.

    load: path -> image (default: the runtime's image loader).
    """
    from tqdm import tqdm

    if load is None:
        from aefabmap_runtime.adapters.frames import load_image as load
    kind = extractor.kind
    d = kind.vector_length
    rng = np.random.default_rng(seed)
    parts: list[MatchPairs] = []
    group = 0
    if warp_images > 0 and files:
        chosen = np.sort(rng.choice(len(files), size=min(warp_images, len(files)), replace=False))
        for i in tqdm(chosen.tolist(), desc="warp pairs", disable=not progress, mininterval=1.0):
            img = load(files[i])
            h = random_homography(img.shape[:2], rng)
            warped = cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)
            fa, fb = extractor.extract(img), extractor.extract(warped)
            idx = warp_pairs(fa, fb, h)
            parts.append(_vectors(kind, fa, fb, idx, group))
            group += 1
    drives = consecutive_frames(files)
    if frame_pairs > 0 and drives:
        take = np.sort(rng.choice(len(drives), size=min(frame_pairs, len(drives)), replace=False))
        for i in tqdm(take.tolist(), desc="frame pairs", disable=not progress, mininterval=1.0):
            pa, pb = drives[i]
            fa, fb = extractor.extract(load(pa)), extractor.extract(load(pb))
            parts.append(_vectors(kind, fa, fb, ratio_matches(fa, fb, kind.distance), group))
            group += 1
    pairs = MatchPairs.concat(parts, d)
    if len(pairs) == 0:
        raise InputError("no matching pairs were found in the training images")
    return pairs


def _vectors(kind, fa: Features, fb: Features, idx: np.ndarray, group: int) -> MatchPairs:
    a = kind.vectors(fa.descriptors[idx[:, 0]]) if len(idx) else np.zeros((0, kind.vector_length), np.float32)
    b = kind.vectors(fb.descriptors[idx[:, 1]]) if len(idx) else np.zeros((0, kind.vector_length), np.float32)
    return MatchPairs(np.asarray(a, np.float32), np.asarray(b, np.float32), np.full(len(idx), group, np.int32))
