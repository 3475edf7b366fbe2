#!/usr/bin/env python
"""Acceptance of geometric verification on TRAINING pairs only (never Lip6 or validation).

Positives: CamVid frames of one drive 1, 2, 3, 5 and 10 frames apart (about 1-10 s); negatives:
frames of two different drives, Scene-15 pairs and CamVid-vs-Scene-15 pairs. Each pair is
verified as the brute-force retry verifies a loop candidate (all descriptors matched with the
ratio test, the a-contrario test), and the acceptance rate is printed per gap for each setting
of `VerificationConfig.method`, `independence`, `ratio_bruteforce` and `upright` (the retry with
upright descriptors when the oriented one fails), with the lowest log10 NFA of the negatives (how
close the nearest unrelated pair came to the -4 bar).

    python scripts/calibrate_verification.py --data DATA --features orb --keypoints 1000 \
        --method lo-ransac magsac --ratio-bruteforce 0.7 0.8 0.9 --upright 0 1 --per-drive 36
"""

from __future__ import annotations

import argparse
import collections
import itertools
import os
import random
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.verify import verification as V
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor

GAPS = (1, 2, 3, 5, 10)


def training_pairs(train: Path, seed: int = 0, per_drive: int = 12):
    """(positives by gap, negatives) as lists of image path pairs; per_drive: start frames
    taken per CamVid drive (evenly spaced), each giving one pair per gap."""
    by_drive = collections.defaultdict(list)
    for p in sorted((train / "camvid").glob("*.jpg")):
        by_drive[p.stem.rsplit("_", 1)[0]].append(p)
    drives = sorted(by_drive)
    pos = {gap: [] for gap in GAPS}
    for d in drives:
        frames = by_drive[d]
        for i in range(0, len(frames) - max(GAPS), max(1, len(frames) // per_drive)):
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
    ap.add_argument("--independence", type=float, nargs="+", default=[0.5])
    ap.add_argument("--ratio-bruteforce", type=float, nargs="+", default=[V.VerificationConfig().ratio_bruteforce])
    ap.add_argument("--method", nargs="+", default=[V.VerificationConfig().method], choices=V.GEOMETRY_METHODS,
                    help="model estimators to compare (default: the runtime's)")
    ap.add_argument("--upright", type=int, nargs="+", default=[int(V.VerificationConfig().upright)], choices=(0, 1),
                    help="1: retry failed pairs with upright descriptors, 0: oriented only (default: the runtime's)")
    ap.add_argument("--per-drive", type=int, default=12, help="pairs per gap and CamVid drive (default 12)")
    args = ap.parse_args()
    kind = get_kind(args.features)
    extractor = FeatureExtractor(FeatureConfig(kind=args.features, max_features=args.keypoints), upright=True)
    cache: dict[Path, object] = {}

    def features(p: Path):
        if p not in cache:
            cache[p] = extractor.extract(load_image(p))
        return cache[p]

    def verify(a: Path, b: Path, config: V.VerificationConfig) -> V.GeometryResult:
        fa, fb = features(a), features(b)
        # No words: only the brute-force matcher runs, as in the retry.
        none_a, none_b = np.full(len(fa), V.NO_WORD, np.int64), np.full(len(fb), V.NO_WORD, np.int64)
        cv2.setRNGSeed(0)  # USAC's sampling: the same pairs give the same verdicts
        radius = V.independence_radius(kind.window_radius(fa.sizes), config)
        return V.verify_pair(fa.keypoints, none_a, fa.descriptors, fa.image_shape, fb.keypoints, none_b,
                             fb.descriptors, fb.image_shape, config, bruteforce=True, distance=kind.distance,
                             radius=radius, q_upright=fa.upright, p_upright=fb.upright)

    pos, neg = training_pairs(args.data / "train", per_drive=args.per_drive)
    for method, independence, ratio, upright in itertools.product(args.method, args.independence,
                                                                  args.ratio_bruteforce, args.upright):
        config = replace(V.VerificationConfig(), method=method, independence=independence, ratio_bruteforce=ratio,
                         upright=bool(upright))
        rates = {gap: np.mean([verify(a, b, config).verified for a, b in pairs]) for gap, pairs in pos.items()}
        negatives = [verify(a, b, config) for a, b in neg]
        wrong = sum(g.verified for g in negatives)
        closest = min((g.nfa for g in negatives if g.nfa is not None), default=float("inf"))
        print(f"{args.features} {args.keypoints} keypoints, {method}, independence {independence}, ratio {ratio}, "
              f"upright {upright}: "
              "positives accepted " + " / ".join(f"{g} frames apart {100 * r:.0f}%" for g, r in rates.items())
              + f" (n={len(pos[GAPS[0]])} per gap); negatives accepted {wrong} of {len(neg)}, "
              f"lowest log10 NFA {closest:.1f}", flush=True)


if __name__ == "__main__":
    main()
