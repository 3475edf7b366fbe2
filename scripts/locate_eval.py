#!/usr/bin/env python
"""Every frame after a map, each located alone ("where am I?", LoopClosureDetector.locate).

The map is built over the sequence's first frames (`--split`; default: up to the first frame the
ground truth pairs with an earlier one); every later frame is then located against it with no
track, no chain and nothing inserted, as a node's locate queryable answers one image
(docs/localization.md). Each answer is right or wrong by the ground truth (`--tolerance`), or
none; a query whose true frames are none of the map's places (the last `--exclude` frames of the
map's run are still held back for the insertion delay) is counted apart.

    python scripts/locate_eval.py --model BUNDLE --images DATA/lip6_outdoor \\
        --gt DATA/lip6_outdoor/ground_truth.npy --split 600 --exclude 50 --tolerance 10 --json locate.json
    python scripts/locate_eval.py --model BUNDLE --images revisits/night-step6/0001TP/images \\
        --gt revisits/night-step6/0001TP/gt.npy --exclude 15 --tolerance 1
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from aefabmap.cli.options import add_detector_options, build_run_config
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.tools.pr_metrics import correct_predictions
from aefabmap_runtime.tools.sequence_eval import load_ground_truth


def first_revisit(gt: np.ndarray) -> int:
    """The first frame the ground truth pairs with an earlier frame (the map ends before it)."""
    rows = np.flatnonzero(np.tril(gt, -1).any(axis=1))
    if not rows.size:
        raise SystemExit("the ground truth has no revisit: give --split")
    return int(rows[0])


def answer_of(where, query: int, gt: np.ndarray, tolerance: int) -> str:
    """right / wrong (by the ground truth, tolerant) or none."""
    if where.frame is None:
        return "none"
    pred = np.full(gt.shape[0], -1)
    pred[query] = where.frame
    return "right" if correct_predictions(pred, gt, tolerance)[query] else "wrong"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--gt", required=True, type=Path)
    ap.add_argument("--split", type=int, default=None, help="the map is built over frames [0, split)")
    ap.add_argument("--tolerance", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None)
    add_detector_options(ap)
    args = ap.parse_args(argv)
    paths = list_images(args.images)
    gt = load_ground_truth(args.gt, len(paths))
    split = first_revisit(gt) if args.split is None else args.split
    det = load_detector(args.model, build_run_config(args).detector)
    for path in paths[:split]:
        det.process(load_image(path))
    places = {int(f) for f in det.map.place_frames() if f >= 0}
    rows = []
    for query in range(split, len(paths)):
        where = det.locate(det.prepare(load_image(paths[query])))
        truth = np.flatnonzero(gt[query, :split])
        rows.append({"query": query, "answer": answer_of(where, query, gt, args.tolerance), "frame": where.frame,
                     "has_truth": bool(truth.size), "truth_in_map": any(int(f) in places for f in truth)})
    sums = {"queries": len(rows), "with_a_true_frame": sum(r["has_truth"] for r in rows),
            "true_frame_a_place": sum(r["truth_in_map"] for r in rows)}
    for kind in ("right", "wrong", "none"):
        sums[kind] = sum(r["answer"] == kind for r in rows)
    sums["wrong_true_frame_a_place"] = sum(r["answer"] == "wrong" and r["truth_in_map"] for r in rows)
    doc = {"model": args.model, "images": str(args.images), "split": split, "map_places": len(places),
           "sums": sums, "answers": rows}
    print(f"{sums['right']} right, {sums['wrong']} wrong ({sums['wrong_true_frame_a_place']} of them with a true "
          f"frame among the map's places), {sums['none']} none of {sums['queries']} queries; "
          f"{sums['with_a_true_frame']} have a true frame in the map's run, {sums['true_frame_a_place']} among its "
          f"{len(places)} places")
    if args.json is not None:
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
