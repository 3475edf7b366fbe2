#!/usr/bin/env python
"""Could any candidate choice have found the revisits an evaluation missed?

For every missed revisit of an `aefabmap eval --frames` run (outcome "miss"), the query is
verified against EVERY frame the ground truth pairs it with, as the brute-force retry verifies a
candidate (same-word matching, then all-pairs matching, the a-contrario test at the runtime
defaults). A miss whose best true frame passes (log10 NFA below the bar) was lost by candidate
choice (FAB-MAP's ranking, the track prior, which candidates get the retry); one whose best true
frame stays far above the bar was lost by geometry itself: the two views share too little
verifiable structure for this criterion, whatever the candidates.

    aefabmap eval --model BUNDLE --images DATA/lip6_outdoor --gt DATA/lip6_outdoor/ground_truth.npy \\
        --fabmap-score llr --frames run.jsonl
    python scripts/miss_reach.py --model BUNDLE --images DATA/lip6_outdoor --frames run.jsonl --json reach.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import AefabmapError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.core.verify.verification import independence_radius, verify_pair


def misses(frames_jsonl: Path) -> list[dict]:
    """The per-frame records (`eval --frames`) of missed revisits."""
    with open(frames_jsonl) as fh:
        return [r for r in map(json.loads, fh) if r.get("outcome") == "miss" and r.get("true_frames")]


def best_true_frame(detector, images: list[Path], record: dict, cache: dict) -> dict:
    """Verify a missed query against each of its true frames; the most significant result."""
    def features(i: int):
        if i not in cache:
            f = detector.extractor.extract(load_image(images[i]))
            cache[i] = (f, detector.words_of(f))
        return cache[i]

    v = detector.config.verification
    q, q_words = features(record["frame"])
    radius = independence_radius(detector.kind.window_radius(q.sizes), v)
    best = {"frame": record["frame"], "true_place_candidate": record.get("true_place_candidate"),
            "best_true_frame": None, "log10_nfa": float("inf"), "inliers": 0, "model": None, "verified": False}
    for t in record["true_frames"]:
        p, p_words = features(int(t))
        g = verify_pair(q.keypoints, q_words, q.descriptors, q.image_shape, p.keypoints, p_words, p.descriptors,
                        p.image_shape, v, bruteforce=True, distance=detector.kind.distance, radius=radius)
        if g.verified > best["verified"] or (g.verified == best["verified"] and g.nfa < best["log10_nfa"]):
            best.update(best_true_frame=int(t), log10_nfa=float(g.nfa), inliers=int(g.inliers), model=g.model,
                        verified=bool(g.verified))
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="the bundle the evaluation ran with")
    ap.add_argument("--images", required=True, type=Path, help="the evaluated image folder")
    ap.add_argument("--frames", required=True, type=Path, help="per-frame records of that run (eval --frames)")
    ap.add_argument("--json", type=Path, help="write the per-miss results and the summary here")
    args = ap.parse_args()
    try:
        detector = load_detector(args.model)
        images = list_images(args.images)
        records = misses(args.frames)
    except (AefabmapError, OSError, ValueError) as exc:
        print(f"miss_reach: {exc}")
        return 2
    bar = detector.config.verification.max_log10_nfa
    cache: dict = {}
    rows = []
    for record in records:
        if not all(0 <= int(i) < len(images) for i in [record["frame"], *record["true_frames"]]):
            print(f"miss_reach: frame {record['frame']} names frames outside the {len(images)} images: wrong --images?")
            return 2
        row = best_true_frame(detector, images, record, cache)
        rows.append(row)
        print(f"frame {row['frame']:5d}  true place among candidates: {str(row['true_place_candidate']):5s}  "
              f"best true frame {row['best_true_frame']}: log10 NFA {row['log10_nfa']:.1f}, {row['inliers']} inliers")
    nfa = np.array([r["log10_nfa"] for r in rows])
    passed = np.array([r["verified"] for r in rows], bool)
    summary = {"misses": len(rows), "bar_log10_nfa": bar, "verifiable": int(passed.sum()),
               "weak": int((~passed & (nfa <= 0)).sum()), "not_significant": int((~passed & (nfa > 0)).sum())}
    print(f"{summary['misses']} misses: {summary['verifiable']} pass against a true frame (lost by candidate choice), "
          f"{summary['weak']} fail with log10 NFA <= 0, {summary['not_significant']} stay above 0")
    if args.json:
        for r in rows:  # JSON has no infinity: no model at all
            r["log10_nfa"] = r["log10_nfa"] if np.isfinite(r["log10_nfa"]) else None
        args.json.write_text(json.dumps({"summary": summary, "misses": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
