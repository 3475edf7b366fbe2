#!/usr/bin/env python
"""Acceptance of geometric verification on TRAINING pairs only (never Lip6 or validation).

Positives: CamVid frames of one drive 1, 2, 3, 5 and 10 frames apart (about 1-10 s); negatives:
frames of two different drives, Scene-15 pairs and CamVid-vs-Scene-15 pairs. Each pair is
verified as a loop candidate is (all descriptors matched, the a-contrario test), and the
acceptance rate is printed per gap for each setting of `VerificationConfig.independence`.

    python scripts/calibrate_verification.py --data DATA --features orb --independence 0 0.5
"""

from __future__ import annotations

import argparse
import collections
import os
import random
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from aefabmap.runtime.adapters.frames import load_image
from aefabmap.runtime.core import verification as V
from aefabmap.runtime.core.feature_kinds import get_kind
from aefabmap.runtime.core.features import FeatureConfig, FeatureExtractor

GAPS = (1, 2, 3, 5, 10)


def training_pairs(train: Path, seed: int = 0):
    """(positives by gap, negatives) as lists of image path pairs."""
    by_drive = collections.defaultdict(list)
    for p in sorted((train / "camvid").glob("*.jpg")):
        by_drive[p.stem.rsplit("_", 1)[0]].append(p)
    drives = sorted(by_drive)
    pos = {gap: [] for gap in GAPS}
    for d in drives:
        frames = by_drive[d]
        for i in range(0, len(frames) - max(GAPS), max(1, len(frames) // 12)):
            for gap in GAPS:
                pos[gap].append((frames[i], frames[i + gap]))
    neg = []
    for i, d in enumerate(drives):
        other = by_drive[drives[(i + 1) % len(drives)]]
        neg += [(by_drive[d][k], other[k]) for k in range(0, min(len(by_drive[d]), len(other)), 6)]
    rng = random.Random(seed)
    scenes = sorted((train / "scene15").rglob("*.jpg"))
    rng.shuffle(scenes)
    neg += [(scenes[k], scenes[k + 1]) for k in range(0, min(200, len(scenes) - 1), 2)]
    camvid = [p for d in drives for p in by_drive[d]]
    neg += [(rng.choice(camvid), scenes[200 + k]) for k in range(min(60, max(0, len(scenes) - 200)))]
    return pos, neg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    repo = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")),
                    help="data root with train/ (default: $AEFABMAP_DATA, else shared/data beside the checkout)")
    ap.add_argument("--features", default="orb")
    ap.add_argument("--keypoints", type=int, default=500)
    ap.add_argument("--independence", type=float, nargs="+", default=[0.0, 0.5])
    args = ap.parse_args()
    kind = get_kind(args.features)
    extractor = FeatureExtractor(FeatureConfig(kind=args.features, max_features=args.keypoints))
    cache: dict[Path, object] = {}

    def features(p: Path):
        if p not in cache:
            cache[p] = extractor.extract(load_image(p))
        return cache[p]

    def accepted(a: Path, b: Path, config: V.VerificationConfig) -> bool:
        fa, fb = features(a), features(b)
        none_a, none_b = np.zeros(len(fa), np.int64), np.zeros(len(fb), np.int64)
        cv2.setRNGSeed(0)  # USAC's sampling: the same pairs give the same verdicts
        radius = V.independence_radius(kind.window_radius(fa.sizes), config)
        return V.verify_pair(fa.keypoints, none_a, fa.descriptors, fa.image_shape, fb.keypoints, none_b,
                             fb.descriptors, fb.image_shape, config, bruteforce=True, distance=kind.distance,
                             radius=radius).verified

    pos, neg = training_pairs(args.data / "train")
    for value in args.independence:
        config = replace(V.VerificationConfig(), independence=value)
        rates = {gap: np.mean([accepted(a, b, config) for a, b in pairs]) for gap, pairs in pos.items()}
        wrong = sum(accepted(a, b, config) for a, b in neg)
        print(f"{args.features} {args.keypoints} keypoints, independence {value}: positives accepted "
              + " / ".join(f"{g} frames apart {100 * r:.0f}%" for g, r in rates.items())
              + f" (n={len(pos[GAPS[0]])} per gap); negatives accepted {wrong} of {len(neg)}", flush=True)


if __name__ == "__main__":
    main()
