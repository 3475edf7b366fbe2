"""Write a model bundle v1 (format defined in aefabmap_runtime.adapters.bundle_reader)."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from aefabmap_runtime.version import __version__
from aefabmap_runtime.errors import BundleError
from aefabmap_runtime.adapters.bundle_reader import (
    BUNDLE_FORMAT,
    BUNDLE_VERSION,
    DESCRIPTOR_WEIGHTS,
    MANIFEST_NAME,
    OBS_FILES,
    TREE_FILES,
    load_bundle,
    sha256_file,
)
from aefabmap_runtime.core.features.features import FeatureConfig
from aefabmap_runtime.core.features.learned_description import LearnedDescription
from aefabmap_runtime.core.rank.tree import ChowLiuTree


def write_bundle(
    out: str | Path,
    *,
    features: FeatureConfig,
    tree: ChowLiuTree,
    training_observations: list[np.ndarray],
    quantizer: dict,
    quantizer_files: dict[str, np.ndarray | Path],
    training_summary: dict,
    detector: dict | None = None,
    learned: LearnedDescription | None = None,
) -> Path:
    """Write a bundle directory atomically and return its path.

    quantizer: manifest entry, e.g. {"type": "kmeans", "files": {"centroids": "vocabulary.npy"}}.
    quantizer_files: file name -> array (saved as .npy) or path of a file to copy (e.g. ONNX).
    learned: the learned descriptor's projection, for features with descriptor "learned".
    An existing bundle at `out` is replaced only once the new one is complete and valid;
    any other existing file or directory there is refused.
    """
    out = Path(out)
    if out.exists() and not (out / MANIFEST_NAME).is_file():
        raise BundleError(f"refusing to overwrite {out}: it exists and is not a model bundle")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        v = tree.size
        arrays = {
            TREE_FILES["parent"]: tree.parent.astype(np.int32),
            TREE_FILES["p"]: tree.p,
            TREE_FILES["a"]: tree.p_given_parent,
            TREE_FILES["b"]: tree.p_given_not_parent,
        }
        rows = [np.unique(np.asarray(o, np.int64)) for o in training_observations]
        arrays[OBS_FILES["indptr"]] = np.concatenate([[0], np.cumsum([r.size for r in rows])]).astype(np.int64)
        idx_dtype = np.uint16 if v <= 65536 else np.uint32
        arrays[OBS_FILES["indices"]] = (np.concatenate(rows) if rows else np.zeros(0)).astype(idx_dtype)
        if learned is not None:
            arrays[DESCRIPTOR_WEIGHTS] = learned.weights
        for name, arr in arrays.items():
            np.save(tmp / name, arr, allow_pickle=False)
        for name, src in quantizer_files.items():
            if isinstance(src, np.ndarray):
                np.save(tmp / name, src, allow_pickle=False)
            else:
                shutil.copyfile(src, tmp / name)
        files = {p.name: sha256_file(p) for p in sorted(tmp.iterdir())}
        sizes = [r.size for r in rows]
        manifest = {
            "format": BUNDLE_FORMAT,
            "format_version": BUNDLE_VERSION,
            "aefabmap_version": __version__,
            "features": features.to_dict(),
            "descriptor_length": features.descriptor_length,
            "vocabulary_size": v,
            "quantizer": quantizer,
            "detector": detector or {"pzge": 0.39, "pzgne": 0.0},
            "tree": {"root": tree.root},
            "training_observations": {
                "count": len(rows),
                "mean_words": float(np.mean(sizes)) if sizes else 0.0,
            },
            "training": training_summary,
            "files": files,
        }
        if learned is not None:
            manifest["descriptor_weights"] = DESCRIPTOR_WEIGHTS
        (tmp / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        written = load_bundle(tmp)  # never leave behind a bundle the runtime would refuse
        if quantizer.get("type") != "ae":
            written.quantizer()  # k-means arrays are validated when the quantiser is built
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            old.rmdir()
            out.rename(old)
            tmp.rename(out)
            shutil.rmtree(old)
        else:
            tmp.rename(out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out
