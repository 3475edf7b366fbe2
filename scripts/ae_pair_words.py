#!/usr/bin/env python
"""Pair words of vocabularies under viewpoint change and synthetic night (issue 34).

Pair words (as scripts/ae_report.py): the share of matching descriptor pairs (one scene point in
two images) whose two descriptors get the same word. Pairs come from test-split training images
(trainer/aefabmap_trainer/multiview.is_test_image, never used for the assign objective's tracks), matched by
position (trainer/aefabmap_trainer/multiview.build_test_pairs):
  viewpoint        image vs a random homography warp of it
  night            image vs its fixed synthetic night (multiview.NIGHT: darker, gamma, noise, blur)
  viewpoint+night  image vs the night of the warp
With --cache, also ae_report.py's held-out pairs (600 warps + 400 CamVid frame pairs, 15 % of
groups held out; the assign objective's tracks may share images with them), split into warps and
frames. Word usage: perplexity (exp of the entropy of word frequencies, in words) and share of
words used, over the test images' descriptors.

    python scripts/ae_pair_words.py --data DATA [--cache DIR] --out OUT.json [--plot CURVES.png] BUNDLE [...]

--plot draws the held-out curves of the word-assignment bundles among them (share of held-out
view pairs on one word, and word perplexity, per epoch; from each manifest's history).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from aefabmap_runtime.adapters.bundle_reader import load_bundle  # noqa: E402
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor  # noqa: E402
from aefabmap_trainer.ae_quantizer import PAIR_VAL_FRACTION  # noqa: E402
from aefabmap_trainer.multiview import build_test_pairs  # noqa: E402
from aefabmap_trainer.train import cached_match_pairs, find_training_images  # noqa: E402

SEED = 0
SETS = ("viewpoint", "night", "viewpoint+night", "old_warps", "old_frames", "old_all")


def pair_words(quantize, pairs) -> float | None:
    """Share of pairs (a, b) whose two descriptors get one word (None without pairs)."""
    if pairs is None or len(pairs) == 0:
        return None
    return round(float(np.mean(quantize(pairs.a) == quantize(pairs.b))), 4)


def usage(words: np.ndarray, k: int) -> dict:
    f = np.bincount(words, minlength=k) / max(words.size, 1)
    nz = f[f > 0]
    return {"perplexity": round(float(np.exp(-(nz * np.log(nz)).sum())), 1), "used": round(float(np.mean(f > 0)), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundles", nargs="+", type=Path)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", "data")))
    ap.add_argument("--cache", type=Path, default=None, help="pair cache of the training runs (old held-out pairs)")
    ap.add_argument("--test-images", type=int, default=300)
    ap.add_argument("--warp-images", type=int, default=600, help="old pair settings (ae_matrix.sh: 600)")
    ap.add_argument("--frame-pairs", type=int, default=400, help="(ae_matrix.sh: 400)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--plot", type=Path, default=None, help="PNG of the assign bundles' held-out curves")
    args = ap.parse_args()

    files = find_training_images([args.data / "train" / "camvid", args.data / "train" / "scene15"])
    sets: dict[str, dict] = {}
    report: dict = {"test_images": args.test_images, "bundles": {}}
    for path in args.bundles:
        b = load_bundle(path)
        m = b.manifest
        fc = FeatureConfig.from_dict(m["features"])
        key = json.dumps(fc.to_dict(), sort_keys=True)
        if key not in sets:
            s = build_test_pairs(files, FeatureExtractor(fc), images=args.test_images, seed=SEED)
            if args.cache is not None:
                _, old = cached_match_pairs(files, fc, args.cache, warp_images=args.warp_images,
                                            frame_pairs=args.frame_pairs, seed=SEED,
                                            show_progress=False).split(PAIR_VAL_FRACTION, SEED)
                s["old_all"] = old
                s["old_warps"] = old.subset(old.group < args.warp_images)
                s["old_frames"] = old.subset(old.group >= args.warp_images)
            sets[key] = s
            report.setdefault("pairs", {})[fc.kind] = {k: len(v) for k, v in s.items()}
        s = sets[key]
        q = m["quantizer"]
        k = int(m["vocabulary_size"])
        entry: dict = {"type": q["type"], "words": k, "objective": (q.get("train") or {}).get("objective", "recon")
                       if q["type"] == "ae" else None}
        for var in (("fp32", "int8") if q["type"] == "ae" else ("fp32",)):
            quant = b.quantizer(var, threads=1)
            entry[var] = {name: pair_words(quant.quantize, s.get(name)) for name in SETS}
            entry[var]["usage"] = usage(quant.quantize(s["viewpoint"].a), k)
        if entry["objective"] == "assign":
            entry["history"] = q["train"].get("history", [])
        report["bundles"][path.name] = entry
        print(path.name, json.dumps(entry), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(markdown(report))
    print(f"wrote {args.out}")
    if args.plot is not None and plot_curves(report, args.plot):
        print(f"wrote {args.plot}")


def markdown(report: dict) -> str:
    head = ("bundle", "variant", *SETS, "usage perplexity", "words used")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in report["bundles"].items():
        for var in ("fp32", "int8"):
            if var not in e:
                continue
            r = e[var]
            cells = [name, var] + ["-" if r[s] is None else f"{100 * r[s]:.1f}" for s in SETS]
            cells += [f"{r['usage']['perplexity']:.0f}", f"{100 * r['usage']['used']:.1f}"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_curves(report: dict, out: Path) -> bool:
    """Held-out view agreement (%) and word perplexity per epoch of the assign bundles; False
    when there are none."""
    from ae_report import plot_epoch_panels  # a sibling script: this one runs from scripts/

    runs = {n: e["history"] for n, e in report["bundles"].items() if e.get("history")}
    if not runs:
        return False
    plot_epoch_panels(runs, [
        ("held-out view pairs on one word (%)", lambda r: 100 * r["val_agreement"]),
        ("held-out word perplexity (words)", lambda r: r["val_perplexity"]),
    ], "epoch (0: start)", out)
    return True


if __name__ == "__main__":
    main()
