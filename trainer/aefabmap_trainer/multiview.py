"""Multi-view tracks of scene points for the AE's word-assignment objective, and the synthetic
test pairs (viewpoint, night) on which vocabularies are compared.

A track is one keypoint of a training image seen in V views: view 0 is the image itself, views
1..V-1 are random homography warps of it (trainer/aefabmap_trainer/match_pairs.random_homography), each with a
random photometric change (darkening, gamma, sensor noise, blur; `photometric`); the last
`light_views` of them may instead be the unwarped image at a random night (`night`), so that
the views also hold pairs that differ in light alone, as a revisit at night does. A keypoint of
view 0 is seen in a warped view when that view has a keypoint that is its mutual nearest
neighbour in position within `tolerance_px` of its projection (match_pairs.warp_pairs): ground
truth by construction. A track is kept when it is seen in at least `min_views` views.

Images whose name hashes into the test split (`is_test_image`) are never used for tracks, so the
test pairs of `build_test_pairs` come from images the objective never trained on.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.features.features import FeatureExtractor
from aefabmap_trainer.match_pairs import MatchPairs, held_out_groups, random_homography, warp_pairs

# One image in TEST_MODULUS (by a hash of its file name) is kept for the test pairs.
TEST_MODULUS = 10
# The fixed synthetic night of the test pairs: gain, gamma, noise sigma (grey levels), blur sigma (px).
NIGHT = {"gain": 0.3, "gamma": 2.2, "noise": 4.0, "blur": 0.8}


def is_test_image(path: Path) -> bool:
    """True for the ~1/TEST_MODULUS of images (by a SHA-256 of the file name) kept out of training tracks."""
    return int(hashlib.sha256(Path(path).name.encode()).hexdigest()[:8], 16) % TEST_MODULUS == 0


def darken(img: np.ndarray, rng: np.random.Generator, *, gain: float, gamma: float, noise: float,
           blur: float) -> np.ndarray:
    """uint8 image (H, W) -> 255 * gain * (img / 255) ** gamma, then Gaussian blur (sigma `blur` px,
    skipped below 0.3) and Gaussian noise (sigma `noise` grey levels, drawn from rng), clipped to uint8."""
    out = 255.0 * gain * (img.astype(np.float32) / 255.0) ** gamma
    if blur >= 0.3:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    if noise > 0:
        out = out + rng.normal(0.0, noise, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def night(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random synthetic night of a uint8 image: gain 0.15-0.5, gamma 1.5-2.5, noise 2-6 grey
    levels, blur 0.5-1.2 px (the range holds the test pairs' NIGHT)."""
    p = dict(gain=rng.uniform(0.15, 0.5), gamma=rng.uniform(1.5, 2.5), noise=rng.uniform(2, 6), blur=rng.uniform(0.5, 1.2))
    return darken(img, rng, **p)


def photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random photometric change of a uint8 image: with probability 1/2 `night`, else "day"
    (gain 0.7-1.1, gamma 0.8-1.25, noise 0-2, no blur)."""
    if rng.random() < 0.5:
        return night(img, rng)
    p = dict(gain=rng.uniform(0.7, 1.1), gamma=rng.uniform(0.8, 1.25), noise=rng.uniform(0, 2), blur=0.0)
    return darken(img, rng, **p)


@dataclass
class Tracks:
    """x: (T, V, D) float32 descriptor vectors of T scene points in V views (view 0 the original
    image); mask: (T, V) bool, the views in which the point was found (x repeats view 0 elsewhere);
    group: (T,) int32 source image of each track (a held-out split keeps images apart)."""

    x: np.ndarray
    mask: np.ndarray
    group: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @property
    def views(self) -> int:
        return int(self.x.shape[1])

    def split(self, val_fraction: float, seed: int) -> tuple["Tracks", "Tracks"]:
        """(train, val) split by whole source images (seeded), as MatchPairs.split."""
        is_val = held_out_groups(self.group, val_fraction, seed)
        return self.subset(~is_val), self.subset(is_val)

    def subset(self, rows: np.ndarray) -> "Tracks":
        return Tracks(self.x[rows], self.mask[rows], self.group[rows])


def build_tracks(files: list[Path], extractor: FeatureExtractor, *, images: int, views: int, seed: int,
                 min_views: int = 3, light_views: int = 0, load=None, tolerance_px: float = 2.0,
                 progress: bool = False) -> Tracks:
    """Tracks from `images` (seeded choice) training images outside the test split, each image
    seen in `views` views (the image + views - 1 copies: warped and photometrically changed, the
    last `light_views` of them unwarped at night); a track is kept when found in at least
    `min_views` >= 3 of them."""
    from tqdm import tqdm

    if not 3 <= min_views <= views:
        raise InputError(f"tracks need 3 <= min_views <= views, got min_views={min_views}, views={views}")
    if not 0 <= light_views < views:
        raise InputError(f"tracks need 0 <= light_views < views, got light_views={light_views}, views={views}")
    if load is None:
        from aefabmap_runtime.adapters.frames import load_image as load
    kind = extractor.kind
    d = kind.vector_length
    pool = [f for f in files if not is_test_image(f)]
    if not pool:
        raise InputError("no training images outside the test split")
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(len(pool), size=min(images, len(pool)), replace=False))
    xs, masks, groups = [], [], []
    for g, i in enumerate(tqdm(chosen.tolist(), desc="tracks", disable=not progress, mininterval=1.0)):
        img = load(pool[i])
        fa = extractor.extract(img)
        matched = []
        for v in range(1, views):
            if v < views - light_views:
                h = random_homography(img.shape[:2], rng)
                warped = cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)
                fb = extractor.extract(photometric(warped, rng))
            else:
                h = np.eye(3)
                fb = extractor.extract(night(img, rng))
            idx = warp_pairs(fa, fb, h, tolerance_px)
            to_b = np.full(len(fa), -1, np.int64)
            to_b[idx[:, 0]] = idx[:, 1]
            matched.append((fb, to_b))
        if not matched or len(fa) == 0:
            continue
        seen = np.stack([to_b >= 0 for _, to_b in matched], axis=1)  # (n_a, views - 1)
        keep = np.flatnonzero(1 + seen.sum(1) >= min_views)
        if keep.size == 0:
            continue
        x = np.empty((keep.size, views, d), np.float32)
        x[:] = kind.vectors(fa.descriptors[keep])[:, None, :]
        for v, (fb, to_b) in enumerate(matched, start=1):
            ok = to_b[keep] >= 0
            if ok.any():
                x[ok, v] = kind.vectors(fb.descriptors[to_b[keep][ok]])
        xs.append(x)
        masks.append(np.concatenate([np.ones((keep.size, 1), bool), seen[keep]], axis=1))
        groups.append(np.full(keep.size, g, np.int32))
    if not xs:
        raise InputError("no multi-view tracks were found in the training images")
    return Tracks(np.concatenate(xs), np.concatenate(masks), np.concatenate(groups))


def build_test_pairs(files: list[Path], extractor: FeatureExtractor, *, images: int, seed: int, load=None,
                     tolerance_px: float = 2.0) -> dict[str, MatchPairs]:
    """Pairs of one scene point on (seeded) test-split images: "viewpoint" (image vs a random
    homography warp of it), "night" (image vs its NIGHT darkening, same geometry) and
    "viewpoint+night" (image vs the darkened warp). Keypoints matched by position, as tracks."""
    if load is None:
        from aefabmap_runtime.adapters.frames import load_image as load
    kind = extractor.kind
    pool = [f for f in files if is_test_image(f)]
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(len(pool), size=min(images, len(pool)), replace=False))
    parts: dict[str, list[MatchPairs]] = {"viewpoint": [], "night": [], "viewpoint+night": []}
    for g, i in enumerate(chosen.tolist()):
        img = load(pool[i])
        fa = extractor.extract(img)
        h = random_homography(img.shape[:2], rng)
        warped = cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)
        for name, other, hh in (("viewpoint", warped, h), ("night", darken(img, rng, **NIGHT), np.eye(3)),
                                ("viewpoint+night", darken(warped, rng, **NIGHT), h)):
            fb = extractor.extract(other)
            idx = warp_pairs(fa, fb, hh, tolerance_px)
            a = kind.vectors(fa.descriptors[idx[:, 0]]) if len(idx) else np.zeros((0, kind.vector_length), np.float32)
            b = kind.vectors(fb.descriptors[idx[:, 1]]) if len(idx) else np.zeros((0, kind.vector_length), np.float32)
            parts[name].append(MatchPairs(np.asarray(a, np.float32), np.asarray(b, np.float32),
                                          np.full(len(idx), g, np.int32)))
    return {k: MatchPairs.concat(v, kind.vector_length) for k, v in parts.items()}
