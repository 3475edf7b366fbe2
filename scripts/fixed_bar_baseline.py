#!/usr/bin/env python
"""A fixed-bar baseline: how far does a simple detector with a raw inlier bar get?

The kind of throwaway prototype loop-closure detectors are often first built as: the bundle's
features (1000 keypoints per frame, all quantised) and vocabulary, the 5 most similar stored
frames by the runtime's tf-idf cosine (idf from the bundle's training observations; outside the
exclusion window), cross-checked brute-force matching, one fundamental-matrix RANSAC per
candidate (`--threshold` pixels of the original images), and the candidate with most inliers; its score is that raw inlier count. It has no notion of
chance: whether N inliers are evidence depends on the sequence, so a bar is only right for
the sequence it was read off.

Printed: the recall at 100 % precision with the bar chosen after the fact on this very
sequence (what a PR sweep reports), and for each `--bars` value the loops such a bar would
publish, how many are wrong, and the recall (tolerant, as the evaluation protocol).

    python scripts/fixed_bar_baseline.py --model BUNDLE --images DATA/lip6_outdoor \\
        --gt DATA/lip6_outdoor/ground_truth.npy --exclude 50 --json lip6.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import AefabmapError
from aefabmap_runtime.adapters.bundle_reader import load_bundle
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.core.rank.bow import BowIndex
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
from aefabmap_runtime.core.words.quantizer import quantize_raw
from aefabmap_runtime.tools.pr_metrics import correct_predictions, evaluate_predictions
from aefabmap_runtime.tools.sequence_eval import load_ground_truth

CANDIDATES = 5
MIN_INLIERS = 15  # below this the baseline makes no prediction at all


def f_inliers(a, b, matcher, threshold: float) -> int:
    """Cross-checked matches of two frames' features, then the inliers of one F RANSAC."""
    if len(a) < 8 or len(b) < 8:
        return 0
    m = matcher.match(a.descriptors, b.descriptors)
    if len(m) < 8:
        return 0
    qa = a.keypoints[[x.queryIdx for x in m]]
    pb = b.keypoints[[x.trainIdx for x in m]]
    _, mask = cv2.findFundamentalMat(qa, pb, cv2.FM_RANSAC, threshold, 0.99)
    return 0 if mask is None else int(mask.sum())


def run(bundle, images: list[Path], exclude: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Best candidate frame (-1: none) and its raw F inlier count, per frame."""
    kind = bundle.features.spec
    extractor = FeatureExtractor(FeatureConfig(**{**bundle.features.to_dict(), "max_features": 1000}))
    quantizer = bundle.quantizer("fp32")
    feats, words = [], []
    for path in images:
        f = extractor.extract(load_image(path))
        feats.append(f)
        words.append(quantize_raw(quantizer, kind, f.descriptors) if len(f) else np.zeros(0, np.int64))
    # The runtime's tf-idf index (`--scorer bow`); frames enter it after the exclusion window, in
    # order, so place ids are frame numbers.
    index = BowIndex(bundle.vocabulary_size, bundle.training_observations)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING if kind.distance == "hamming" else cv2.NORM_L2, crossCheck=True)
    best = np.full(len(images), -1, np.int64)
    score = np.zeros(len(images))
    for i in range(exclude + 1, len(images)):
        index.add(words[i - exclude - 1])
        top = np.argsort(-index.similarity(words[i]), kind="stable")[:CANDIDATES]
        counts = [(f_inliers(feats[i], feats[j], matcher, threshold), int(j)) for j in top]
        inliers, frame = max(counts, key=lambda c: c[0])
        if inliers >= MIN_INLIERS:
            best[i], score[i] = frame, inliers
    return best, score


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="bundle whose features and vocabulary the baseline uses")
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--gt", required=True, type=Path, help="bool N x N ground truth")
    ap.add_argument("--exclude", type=int, default=50, help="exclusion window in frames (default 50)")
    ap.add_argument("--threshold", type=float, default=1.0, help="F RANSAC threshold, original pixels (default 1)")
    ap.add_argument("--bars", type=int, nargs="+", default=[21, 30, 40, 50, 65], help="fixed inlier bars to report")
    ap.add_argument("--tolerance", type=int, default=10)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    try:
        bundle = load_bundle(args.model)
        images = list_images(args.images)
        gt = load_ground_truth(args.gt, len(images))
        cv2.setNumThreads(1)
        best, score = run(bundle, images, args.exclude, args.threshold)
    except (AefabmapError, OSError, ValueError) as exc:
        print(f"fixed_bar_baseline: {exc}")
        return 2
    metrics = evaluate_predictions(best, score, gt, args.tolerance)
    correct = correct_predictions(best, np.tril(gt, -1), args.tolerance)
    relevant = metrics["relevant_frames"]
    print(f"bar chosen after the fact: {100 * metrics['recall_at_100p_tolerant']:.1f} % recall at 100 % precision "
          f"(bar {metrics['threshold_at_100p_tolerant']}), {relevant} revisit frames")
    bars = []
    for bar in args.bars:
        published = score >= bar
        row = {"bar": bar, "published": int(published.sum()), "wrong": int((published & ~correct).sum()),
               "recall": float((published & correct).sum() / max(relevant, 1))}
        bars.append(row)
        print(f"bar {bar:3d}: {row['published']:4d} loops published, {row['wrong']:3d} wrong, "
              f"recall {100 * row['recall']:.1f} %")
    if args.json:
        out = {k: metrics[k] for k in ("frames", "relevant_frames", "predictions", "recall_at_100p_tolerant",
                                       "threshold_at_100p_tolerant", "auc_tolerant", "false_positives")}
        out.update(model=str(args.model), images=str(args.images), exclude=args.exclude, threshold=args.threshold,
                   bars=bars)
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
