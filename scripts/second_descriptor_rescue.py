#!/usr/bin/env python
"""Would a second descriptor rescue the pairs an ORB run found weak, and at what risk?

Offline, from the per-frame records of an `aefabmap eval --frames` run (the first descriptor,
ORB's tests): for every frame that run did not publish, each checked candidate whose log10 NFA
lies between the bar and a gate (`--gates`) is verified again with the second bundle's
descriptors (`--second`, e.g. `train --descriptor learned`), as the brute-force retry verifies
(all-pairs matching, then the upright descriptors). A frame is rescued by its most significant
such pair whose second log10 NFA passes the bar with log10 2 added (two descriptors tried); each
rescue is right or wrong by the ground truth (`--tolerance`).

The gate asks the first descriptor for some support of its own (a log10 NFA below the gate)
before the second may decide: a pair the first descriptor sees nothing in is not retried. A
rescued frame does not start a track here, so the rescues a run would make after it are not
counted (a lower bound on the gain).

    aefabmap eval --model ORB_BUNDLE --images DIR --gt GT.npy --exclude 15 --tolerance 1 \\
        --fabmap-score llr --frames orb.jsonl
    python scripts/second_descriptor_rescue.py --second LEARNED_BUNDLE --images DIR --gt GT.npy \\
        --frames orb.jsonl --tolerance 1 --json rescue.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import AefabmapError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.tools.pr_metrics import correct_predictions
from aefabmap_runtime.tools.sequence_eval import load_ground_truth

#: Gates tried by default (log10 NFA of the first descriptor): the textbook a-contrario bar
#: (NFA < 1), two stricter ones, and none at all (every checked candidate above the bar).
DEFAULT_GATES = (0.0, -1.0, -2.0, math.inf)


class SecondDescriptor:
    """Verifies (query, stored frame) pairs of a sequence with a bundle's descriptors by the
    detector's own pair check (`LoopClosureDetector.place_check`) against the stored frame in
    store form, as the brute-force retry does; each frame is extracted once."""

    def __init__(self, model: str | Path, images: list[Path]) -> None:
        self.detector = load_detector(model)
        self.images = images
        self._frames: dict[int, tuple] = {}

    def _of(self, frame: int) -> tuple:
        """(features, words, store form) of one frame."""
        if frame not in self._frames:
            f = self.detector.extractor.extract(load_image(self.images[frame]))
            words = self.detector.words_of(f)
            place = self.detector.map.store.pack(f.keypoints, words, f.descriptors, f.image_shape, f.upright)
            self._frames[frame] = (f, words, place)
        return self._frames[frame]

    def log10_nfa(self, query: int, stored: int) -> tuple[float, int]:
        """(log10 NFA, inliers) of the pair: all-pairs matching, then upright; inf without a model."""
        q, q_words, _ = self._of(query)
        g = self.detector.place_check(q, q_words)(self._of(stored)[2], bruteforce=True, retry_only=True, upright=True)
        return float(g.nfa), int(g.inliers)


def retries(records: list[dict], second: SecondDescriptor, bar: float, widest_gate: float) -> list[dict]:
    """Per unpublished frame with a checked candidate between the bar and the widest gate: the
    candidates' first and second log10 NFAs ({frame, tries: [{stored, first, second, inliers}]})."""
    out = []
    for rec in records:
        if rec.get("verified"):
            continue
        tries = []
        for c in rec.get("candidates", []):
            first = c.get("nfa")
            if not c.get("checked") or first is None or c.get("frame") is None or not bar <= first < widest_gate:
                continue
            nfa, inliers = second.log10_nfa(int(rec["frame"]), int(c["frame"]))
            tries.append({"stored": int(c["frame"]), "first": float(first), "second": nfa, "inliers": inliers})
        if tries:
            out.append({"frame": int(rec["frame"]), "tries": tries})
    return out


def rescued(tried: list[dict], gate: float, bar: float) -> dict[int, dict]:
    """{frame: the try that rescues it} under one gate: first log10 NFA below the gate, second
    below the bar with log10 2 added for the two descriptors; the most significant second."""
    out = {}
    for row in tried:
        ok = [t for t in row["tries"] if t["first"] < gate and t["second"] + math.log10(2) < bar]
        if ok:
            out[row["frame"]] = min(ok, key=lambda t: t["second"])
    return out


def score(records: list[dict], tried: list[dict], gates: list[float], gt: np.ndarray, tolerance: int,
          bar: float) -> list[dict]:
    """Per gate: the first run's right and wrong loops, the rescues right and wrong (with the
    wrong ones listed as (frame, stored frame, first, second log10 NFA))."""
    n = len(records)
    first = np.full(n, -1, np.int64)
    for rec in records:
        if rec.get("verified") and rec.get("chosen_frame") is not None:
            first[int(rec["frame"])] = int(rec["chosen_frame"])
    first_right = correct_predictions(first, gt, tolerance)
    rows = []
    for gate in gates:
        chosen = rescued(tried, gate, bar)
        pred = np.full(n, -1, np.int64)
        for f, t in chosen.items():
            pred[f] = t["stored"]
        right = correct_predictions(pred, gt, tolerance)
        wrong = [(f, t["stored"], round(t["first"], 2), round(t["second"], 2)) for f, t in sorted(chosen.items())
                 if not right[f]]
        rows.append({"gate": gate if math.isfinite(gate) else None,
                     "first_right": int(first_right[first >= 0].sum()),
                     "first_wrong": int((~first_right[first >= 0]).sum()),
                     "rescued_right": int(right[pred >= 0].sum()), "rescued_wrong": len(wrong), "wrong": wrong,
                     "pairs_tried": sum(1 for row in tried for t in row["tries"] if t["first"] < gate)})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--second", required=True, help="the bundle whose descriptors verify again")
    ap.add_argument("--images", required=True, type=Path, help="the evaluated image folder")
    ap.add_argument("--gt", required=True, type=Path, help="its ground truth (N, N) .npy")
    ap.add_argument("--frames", required=True, type=Path, help="per-frame records of the first run (eval --frames)")
    ap.add_argument("--tolerance", type=int, default=10, help="frames a right loop may be off (as eval's)")
    ap.add_argument("--gates", type=float, nargs="+", default=list(DEFAULT_GATES),
                    help="first log10 NFA below which the second descriptor may decide (inf: always)")
    ap.add_argument("--json", type=Path, help="write the table and every pair tried here")
    args = ap.parse_args(argv)
    try:
        images = list_images(args.images)
        gt = np.tril(load_ground_truth(args.gt, len(images)).astype(bool), -1)
        with open(args.frames) as fh:
            records = [json.loads(line) for line in fh if line.strip()]
        if [r.get("frame") for r in records] != list(range(len(images))):
            raise ValueError(f"{args.frames} does not hold one record per image of {args.images}, in order")
        second = SecondDescriptor(args.second, images)
    except (AefabmapError, OSError, ValueError) as exc:
        print(f"second_descriptor_rescue: {exc}")
        return 2
    bar = second.detector.config.verification.max_log10_nfa
    tried = retries(records, second, bar, max(args.gates))
    rows = score(records, tried, args.gates, gt, args.tolerance, bar)
    for r in rows:
        gate = "none" if r["gate"] is None else f"{r['gate']:g}"
        print(f"gate {gate:>5}: first {r['first_right']} right / {r['first_wrong']} wrong, rescued "
              f"{r['rescued_right']} right / {r['rescued_wrong']} wrong ({r['pairs_tried']} pairs tried) {r['wrong']}")
    if args.json:
        for row in tried:  # JSON has no infinity: no model at all
            for t in row["tries"]:
                t["second"] = t["second"] if math.isfinite(t["second"]) else None
        args.json.write_text(json.dumps({"table": rows, "tried": tried}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
