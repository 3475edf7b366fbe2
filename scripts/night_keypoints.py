#!/usr/bin/env python
"""What a synthetic night takes from a frame's keypoints: detection first, then matching.

Each image (the test split of the training images, `trainer.multiview.is_test_image`: nothing was
fitted on them) is seen by day and again under a photometric condition with the same geometry:
the synthetic night of the training revisits (`trainer.multiview.NIGHT`) and its parts one at a
time (gain, gamma, blur, sensor noise), with day noise alone as the control. The bundle's
detector extracts both, with its verification budget and upright copies, and for every day
keypoint the tool asks, in turn:

- repeated: the night frame has a keypoint on the same pyramid level within REPEAT_RADIUS of
  that level's pixels (the same scene point, since nothing moved);
- matched: the verification's all-pairs matcher (`verification.match_all`: the distance cap and
  the ratio test) pairs the night keypoint with it, by the oriented descriptors, by the upright
  ones, or by either.

Shares are of the day keypoints. A keypoint that is not repeated cannot be matched, whatever
the descriptor; a repeated one that is not matched is the descriptor's loss.

    python scripts/night_keypoints.py --model bundles/orb_kmeans_3000 --data DATA --json night_keypoints.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.features.features import Features, to_gray
from aefabmap_runtime.core.verify.verification import match_all
from aefabmap_runtime.errors import AefabmapError
from aefabmap_trainer.multiview import NIGHT, darken, is_test_image

#: A repeated keypoint lies within this many pixels of its level (ORB's pyramid) of the day one.
REPEAT_RADIUS = 2.0
#: ORB's patch (px of its level): a keypoint's size is the patch times its level's scale.
PATCH = 31.0
#: The conditions, as `darken`'s gain, gamma, noise (grey levels) and blur (px): the night and
#: each of its parts alone, and day noise as the control.
CONDITIONS = {
    "day noise": {"gain": 1.0, "gamma": 1.0, "noise": 2.0, "blur": 0.0},
    "gain": {"gain": NIGHT["gain"], "gamma": 1.0, "noise": 0.0, "blur": 0.0},
    "gamma": {"gain": 1.0, "gamma": NIGHT["gamma"], "noise": 0.0, "blur": 0.0},
    "gain and gamma": {"gain": NIGHT["gain"], "gamma": NIGHT["gamma"], "noise": 0.0, "blur": 0.0},
    "gain, gamma, blur": {"gain": NIGHT["gain"], "gamma": NIGHT["gamma"], "noise": 0.0, "blur": NIGHT["blur"]},
    "night": dict(NIGHT),
}
SHARES = ("repeated", "matched_oriented", "matched_upright", "matched_either")


def repeated_partner(day: Features, night: Features) -> np.ndarray:
    """(N,) index of each day keypoint's repeated night keypoint (module doc), -1 where none."""
    partner = np.full(len(day), -1, np.int64)
    if len(day) == 0 or len(night) == 0:
        return partner
    for size in np.unique(day.sizes):
        d = np.flatnonzero(day.sizes == size)
        n = np.flatnonzero(np.isclose(night.sizes, size, rtol=1e-4))
        if n.size == 0:
            continue
        dist, j = cKDTree(night.keypoints[n]).query(day.keypoints[d])
        near = dist <= REPEAT_RADIUS * size / PATCH  # the level's pixels in the image's
        partner[d[near]] = n[j[near]]
    return partner


def matched(partner: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(N,) bool: the matcher's pairs (K, 2) (night index, day index) hold (partner[i], i)."""
    hit = np.zeros(partner.size, bool)
    if pairs.size:
        hit[pairs[:, 1]] = partner[pairs[:, 1]] == pairs[:, 0]
    return hit & (partner >= 0)


def image_counts(detector, gray: np.ndarray, day: Features, condition: dict, rng: np.random.Generator) -> dict:
    """Counts of one image `gray` (its day features `day`) under one condition: day keypoints and
    each of SHARES."""
    night = detector.extractor.extract(darken(gray, rng, **condition))
    partner = repeated_partner(day, night)
    config, distance = detector.config.verification, detector.kind.distance
    oriented = matched(partner, match_all(night.descriptors, day.descriptors, config, distance=distance))
    upright = (matched(partner, match_all(night.upright, day.upright, config, distance=distance))
               if day.upright is not None and night.upright is not None else np.zeros(len(day), bool))
    return {"keypoints": len(day), "repeated": int((partner >= 0).sum()), "matched_oriented": int(oriented.sum()),
            "matched_upright": int(upright.sum()), "matched_either": int((oriented | upright).sum())}


def measure(detector, images: list[Path], conditions: dict, seed: int = 0, show_progress: bool = True) -> dict:
    """{condition: counts summed over `images` and the SHARES of the day keypoints}; each image is
    read and extracted by day once, and its noise drawn from a generator seeded by `seed` and its
    index, the same for every condition."""
    out = {name: {"keypoints": 0, **{k: 0 for k in SHARES}} for name in conditions}
    for i, path in enumerate(tqdm(images, desc="images", disable=not show_progress, mininterval=1.0)):
        gray = to_gray(load_image(path))
        day = detector.extractor.extract(gray)
        for name, condition in conditions.items():
            counts = image_counts(detector, gray, day, condition, np.random.default_rng([seed, i]))
            for k, total in counts.items():
                out[name][k] += total
    for total in out.values():
        total["shares"] = {k: total[k] / max(total["keypoints"], 1) for k in SHARES}
    return out


def test_split(data: Path, count: int) -> list[Path]:
    """The first `count` test-split images of DATA/train/camvid, by name."""
    return [p for p in sorted((data / "train" / "camvid").glob("*.jpg")) if is_test_image(p)][:count]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, required=True, help="bundle whose detector and descriptor to use")
    ap.add_argument("--data", type=Path, required=True, help="the data root (its train/camvid)")
    ap.add_argument("--images", type=int, default=60, help="test-split images to use (default 60)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the synthetic noise")
    ap.add_argument("--json", type=Path, help="write the counts and shares here")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        detector = load_detector(args.model)
        images = test_split(args.data, args.images)
        if not images:
            raise AefabmapError(f"no test-split image in {args.data / 'train' / 'camvid'}")
        result = measure(detector, images, CONDITIONS, args.seed, not args.no_progress)
    except (AefabmapError, OSError) as exc:
        print(f"night_keypoints: {exc}", file=sys.stderr)
        return 1
    print(f"{len(images)} images, {args.model}; shares of the day keypoints")
    print(f"{'condition':<20}" + "".join(f"{k:>18}" for k in SHARES))
    for name, row in result.items():
        print(f"{name:<20}" + "".join(f"{row['shares'][k]:>18.3f}" for k in SHARES))
    if args.json:
        args.json.write_text(json.dumps({"model": str(args.model), "images": len(images), "seed": args.seed,
                                         "repeat_radius": REPEAT_RADIUS, "conditions": CONDITIONS,
                                         "results": result}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
