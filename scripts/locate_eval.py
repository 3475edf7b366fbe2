#!/usr/bin/env python
"""Every frame after a map, each located alone ("where am I?", LoopClosureDetector.locate).

The map is built over the sequence's first frames (`--split`; default: up to the first frame the
ground truth pairs with an earlier one); every later frame is then located against it with no
track, no chain and nothing inserted, as a node's locate queryable answers one image
(docs/localization.md). Each answer is right or wrong by the ground truth (`--tolerance`), or
none; a query whose true frames are none of the map's places (the last `--exclude` frames of the
map's run are still held back for the insertion delay) is counted apart.

`--stream` also runs the later frames as a localizing node takes them (`eval --localize`): the map
saved and loaded read-only, the frames numbered on from it, its held-back frames entering on their
schedule, the track leading; its verified places are scored the same way.

    python scripts/locate_eval.py --model BUNDLE --images DATA/lip6_outdoor \\
        --gt DATA/lip6_outdoor/ground_truth.npy --split 600 --exclude 50 --tolerance 10 --json locate.json
    python scripts/locate_eval.py --model BUNDLE --images revisits/night-step6/0001TP/images \\
        --gt revisits/night-step6/0001TP/gt.npy --exclude 15 --tolerance 1 --stream
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


def answer_of(frame: int | None, query: int, gt: np.ndarray, tolerance: int) -> str:
    """right / wrong (by the ground truth, tolerant) or none, for query `query` answered `frame`."""
    if frame is None:
        return "none"
    pred = np.full(gt.shape[0], -1)
    pred[query] = frame
    return "right" if correct_predictions(pred, gt, tolerance)[query] else "wrong"


def tally(rows: list[dict]) -> dict:
    """{"right": n, "wrong": n, "none": n} of answer rows."""
    return {kind: sum(r["answer"] == kind for r in rows) for kind in ("right", "wrong", "none")}


def streamed(args, det, config, gt: np.ndarray) -> dict:
    """right / wrong / none of the later frames run as a localizing node takes them against the
    map of `det`, saved and loaded read-only (tools/localize_eval.py), and the answers."""
    import logging
    import tempfile

    from aefabmap_runtime.adapters.node_state import new_map_saver
    from aefabmap_runtime.tools.localize_eval import localize_sequence

    with tempfile.TemporaryDirectory() as tmp:
        new_map_saver(Path(tmp) / "map", logging.getLogger("aefabmap.locate_eval"))(det)
        _, run = localize_sequence(args.model, args.images, args.gt, Path(tmp) / "map", config, args.tolerance,
                                   show_progress=False)
    frames = [(r.sequence, r.verified_frame if r.verified else None) for r in run.run.results]
    answers = [{"query": q, "frame": f, "answer": answer_of(f, q, gt, args.tolerance)} for q, f in frames]
    return tally(answers) | {"answers": answers}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--gt", required=True, type=Path)
    ap.add_argument("--split", type=int, default=None, help="the map is built over frames [0, split)")
    ap.add_argument("--tolerance", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--stream", action="store_true", help="also run the later frames as eval --localize does")
    add_detector_options(ap)
    args = ap.parse_args(argv)
    paths = list_images(args.images)
    gt = load_ground_truth(args.gt, len(paths))
    split = first_revisit(gt) if args.split is None else args.split
    config = build_run_config(args).detector
    det = load_detector(args.model, config)
    for path in paths[:split]:
        det.process(load_image(path))
    places = {int(f) for f in det.map.place_frames() if f >= 0}
    rows = []
    for query in range(split, len(paths)):
        where = det.locate(det.prepare(load_image(paths[query])))
        truth = np.flatnonzero(gt[query, :split])
        rows.append({"query": query, "answer": answer_of(where.frame, query, gt, args.tolerance), "frame": where.frame,
                     "has_truth": bool(truth.size), "truth_in_map": any(int(f) in places for f in truth)})
    sums = {"queries": len(rows), "with_a_true_frame": sum(r["has_truth"] for r in rows),
            "true_frame_a_place": sum(r["truth_in_map"] for r in rows)} | tally(rows)
    sums["wrong_true_frame_a_place"] = sum(r["answer"] == "wrong" and r["truth_in_map"] for r in rows)
    doc = {"model": args.model, "images": str(args.images), "split": split, "map_places": len(places),
           "sums": sums, "answers": rows}
    print(f"{sums['right']} right, {sums['wrong']} wrong ({sums['wrong_true_frame_a_place']} of them with a true "
          f"frame among the map's places), {sums['none']} none of {sums['queries']} queries; "
          f"{sums['with_a_true_frame']} have a true frame in the map's run, {sums['true_frame_a_place']} among its "
          f"{len(places)} places")
    if args.stream:
        doc["streamed"] = streamed(args, det, config, gt)
        print(f"streamed: {doc['streamed']['right']} right, {doc['streamed']['wrong']} wrong, "
              f"{doc['streamed']['none']} none")
    if args.json is not None:
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
