#!/usr/bin/env python
"""Re-vocabulary an AE bundle with a two-level latent vocabulary tree (faster word search).

Keeps the bundle's encoder (fp32 and int8 ONNX graphs), encodes the same training sample the
AE run clustered, fits a LatentTree (trainer/aefabmap_trainer/latent_vocabulary.py) of the same size K, swaps the
graphs' flat arg-min for the tree search (export/aefabmap_export/onnx_export.attach_tree_search), re-quantises
the training images and re-learns the Chow-Liu tree. Usage:

    python scripts/ae_tree_bundle.py --data DATA --cache bundles/cache --branches 64 SRC_BUNDLE OUT_BUNDLE
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import onnx  # noqa: E402

from aefabmap_export.bundle_writer import write_bundle  # noqa: E402
from aefabmap_export.onnx_export import attach_tree_search  # noqa: E402
from aefabmap_runtime.adapters.bundle_reader import load_bundle  # noqa: E402
from aefabmap_runtime.core.features.features import FeatureConfig  # noqa: E402
from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer  # noqa: E402
from aefabmap_trainer.chow_liu import fit_chow_liu  # noqa: E402
from aefabmap_trainer.latent_vocabulary import fit_latent_tree  # noqa: E402
from aefabmap_trainer.train import cached_training_vectors, find_training_images, sample_vectors  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--branches", type=int, default=64)
    ap.add_argument("--samples", type=int, default=250_000, help="training vectors clustered (the AE run's)")
    args = ap.parse_args()

    t0 = time.perf_counter()
    src = load_bundle(args.src)
    m = src.manifest
    q = m["quantizer"]
    if q["type"] != "ae":
        raise SystemExit(f"{args.src} is not an AE bundle")
    fc = FeatureConfig.from_dict(m["features"])
    words, seed = int(m["vocabulary_size"]), int(m["training"]["seed"])
    files = find_training_images([args.data / "train" / d for d in m["training"]["image_dirs"]])
    per_image = cached_training_vectors(files, fc, args.cache, False)
    sample = sample_vectors(per_image, fc.spec, args.samples, seed)
    d = fc.descriptor_length
    flat = OnnxQuantizer(args.src / q["files"]["fp32"], vocabulary_size=words, descriptor_length=d)
    codes = flat.encode(sample)
    t1 = time.perf_counter()
    tree = fit_latent_tree(codes, words, branches=args.branches, seed=seed)
    tree_s = time.perf_counter() - t1
    with tempfile.TemporaryDirectory() as work:
        paths = {}
        for var, name in q["files"].items():
            model = onnx.load(str(args.src / name))
            attach_tree_search(model, tree)
            onnx.checker.check_model(model)
            paths[name] = Path(work) / name
            paths[name].write_bytes(model.SerializeToString(deterministic=True))
        qt = {v: OnnxQuantizer(paths[n], vocabulary_size=tree.size, descriptor_length=d) for v, n in q["files"].items()}
        w_tree = qt["fp32"].quantize(sample[:20_000])
        if not np.array_equal(w_tree, tree.assign(codes[:20_000])):
            print("warning: graph and numpy tree search differ on", int(np.sum(w_tree != tree.assign(codes[:20_000]))))
        observations = [np.unique(qt["fp32"].quantize(fc.spec.vectors(raw))) if len(raw) else np.zeros(0, np.int64)
                        for raw in per_image]
        chow = fit_chow_liu(observations, tree.size)
        entry = copy.deepcopy(q)
        entry["search"] = {"type": "tree", "branches": args.branches, "leaf_block": int(tree.leaves.shape[1]),
                           "fit_s": round(tree_s, 1), "source_bundle": args.src.name}
        entry["int8_agreement"] = round(float(np.mean(qt["int8"].quantize(sample[:20_000]) == w_tree)), 6)
        summary = dict(m["training"])
        summary["mean_words_per_image"] = float(np.mean([o.size for o in observations]))
        out = write_bundle(args.out, features=fc, tree=chow, training_observations=observations, quantizer=entry,
                           quantizer_files=paths, training_summary=summary)
    print(json.dumps({"bundle": str(out), "seconds": round(time.perf_counter() - t0, 1), "search": entry["search"],
                      "int8_agreement_train": entry["int8_agreement"]}))


if __name__ == "__main__":
    main()
