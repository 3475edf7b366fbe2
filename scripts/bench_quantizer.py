#!/usr/bin/env python
"""Benchmark the AE-VQ quantiser: train (ORB and SIFT), then time fp32 vs int8 ONNX on one thread.

Prints and writes JSON: training time/loss, int8 agreement, ms per 500 descriptors, file sizes.
Training images: <data>/train (never lip6_outdoor); timing vectors come from scene15 images
not used for training. Usage:
    python scripts/bench_quantizer.py --data "$AEFABMAP_DATA" --out out/bench_quantizer.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from aefabmap.runtime.core.onnx_quantizer import OnnxQuantizer
from aefabmap.trainer.ae_quantizer import build_ae_quantizer, descriptor_sample
from aefabmap.trainer.autoencoder import AeConfig


def time_quantizer(q: OnnxQuantizer, x: np.ndarray, repeats: int) -> float:
    """Median milliseconds of one quantize() call on x."""
    q.quantize(x)  # warm-up: first run allocates
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        q.quantize(x)
        times.append((time.perf_counter() - t) * 1000)
    return float(np.median(times))


def main() -> None:
    repo = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")))
    ap.add_argument("--out", type=Path, default=repo / "out" / "bench_quantizer.json")
    ap.add_argument("--kinds", nargs="+", default=["orb", "sift"])
    ap.add_argument("--words", type=int, default=2000)
    ap.add_argument("--train-images", type=int, default=400)
    ap.add_argument("--max-descriptors", type=int, default=50_000)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="torch threads for training")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    train_dir = args.data / "train"
    images = sorted(train_dir.rglob("*.jpg"))
    if not images:
        raise SystemExit(f"no training images under {train_dir}")
    rng = np.random.default_rng(args.seed)
    chosen = [images[i] for i in np.sort(rng.choice(len(images), min(args.train_images, len(images)), replace=False))]
    held_out = [p for p in sorted((train_dir / "scene15").rglob("*.jpg")) if p not in set(chosen)][:40]

    report: dict = {"words": args.words, "threads_inference": 1, "kinds": {}}
    work = args.out.parent / "bench_models"
    for kind in args.kinds:
        t = time.perf_counter()
        vectors = descriptor_sample(chosen, kind)
        feat_s = time.perf_counter() - t
        cfg = AeConfig(max_epochs=args.epochs, max_descriptors=args.max_descriptors, threads=args.threads)
        t = time.perf_counter()
        manifest = build_ae_quantizer(vectors, words=args.words, seed=args.seed, feature_kind=kind,
                                      out_dir=work / kind, config=cfg)
        build_s = time.perf_counter() - t
        x = descriptor_sample(held_out, kind, limit=500)
        entry = {"descriptors_available": int(vectors.shape[0]), "features_s": round(feat_s, 1),
                 "build_s": round(build_s, 1), "manifest": manifest}
        for variant in ("fp32", "int8"):
            path = work / kind / manifest["files"][variant]
            q = OnnxQuantizer(path, vocabulary_size=args.words, descriptor_length=vectors.shape[1], threads=1)
            entry[f"ms_per_{x.shape[0]}_{variant}"] = round(time_quantizer(q, x, args.repeats), 2)
            entry[f"size_bytes_{variant}"] = path.stat().st_size
        w32 = OnnxQuantizer(work / kind / manifest["files"]["fp32"], vocabulary_size=args.words,
                            descriptor_length=vectors.shape[1]).quantize(x)
        w8 = OnnxQuantizer(work / kind / manifest["files"]["int8"], vocabulary_size=args.words,
                           descriptor_length=vectors.shape[1]).quantize(x)
        entry["int8_agreement_held_out"] = round(float(np.mean(w32 == w8)), 4)
        report["kinds"][kind] = entry
        print(json.dumps({kind: {k: v for k, v in entry.items() if k != "manifest"}
                          | {"train": manifest["train"] | {"config": None}, "int8_agreement": manifest["int8_agreement"]}},
                         indent=1), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
