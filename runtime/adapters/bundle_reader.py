"""Model bundle v1: the one contract between the trainer/exporter and the runtime.

A bundle is a directory:
    manifest.json                  format, version, features, vocabulary, detector, checksums
    tree_parent.npy  (V,) int32    Chow-Liu parent of each word (root: itself)
    tree_p.npy, tree_a.npy, tree_b.npy  (V,) float64   P(z), P(z|parent), P(z|not parent)
    train_obs_indptr.npy (M+1,) int64, train_obs_indices.npy (nnz,) uint16|uint32
                                   training observations (CSR rows of word ids) for the
                                   sampled new-place model and tf-idf weights
    quantizer files                kmeans: vocabulary.npy (V, D) float32 centroids;
                                   ae: quantizer_fp32.onnx, quantizer_int8.onnx
Arrays load with allow_pickle=False. Every file is listed in manifest["files"] with its sha256;
the runtime refuses a bundle whose version, shapes or checksums do not match.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aefabmap.errors import BundleError, ConfigError, InputError
from aefabmap.runtime.core.features import FeatureConfig
from aefabmap.runtime.core.tree import ChowLiuTree

BUNDLE_FORMAT = "aefabmap-bundle"
BUNDLE_VERSION = 1
MANIFEST_NAME = "manifest.json"
TREE_FILES = {"parent": "tree_parent.npy", "p": "tree_p.npy", "a": "tree_a.npy", "b": "tree_b.npy"}
OBS_FILES = {"indptr": "train_obs_indptr.npy", "indices": "train_obs_indices.npy"}
QUANTIZER_TYPES = ("kmeans", "ae")


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class ModelBundle:
    """A validated model bundle loaded from disk.

    training_observations: list of M sorted word-id arrays (int64).
    """

    path: Path
    manifest: dict
    features: FeatureConfig
    tree: ChowLiuTree
    training_observations: list[np.ndarray] = field(repr=False)

    @property
    def vocabulary_size(self) -> int:
        return int(self.manifest["vocabulary_size"])

    @property
    def descriptor_length(self) -> int:
        return int(self.manifest["descriptor_length"])

    @property
    def quantizer_type(self) -> str:
        return str(self.manifest["quantizer"]["type"])

    @property
    def detector(self) -> dict:
        return dict(self.manifest.get("detector", {"pzge": 0.39, "pzgne": 0.0}))

    def quantizer(self, variant: str = "fp32", threads: int = 1):
        """Build the bundle's quantiser (Quantizer protocol). variant: "fp32" | "int8" (ae only)."""
        q = self.manifest["quantizer"]
        files = q["files"]
        if self.quantizer_type == "kmeans":
            from aefabmap.runtime.core.quantizer import NearestCentroidQuantizer

            centroids = _load_array(self.path, files["centroids"])
            if centroids.shape != (self.vocabulary_size, self.descriptor_length):
                raise BundleError(
                    f"{self.path}: vocabulary has shape {centroids.shape}, manifest says "
                    f"({self.vocabulary_size}, {self.descriptor_length})"
                )
            return NearestCentroidQuantizer(centroids)
        if variant not in files:
            raise ConfigError(f"bundle {self.path} has no {variant!r} quantiser; it has {sorted(files)}")
        from aefabmap.runtime.core.onnx_quantizer import OnnxQuantizer

        return OnnxQuantizer(
            self.path / files[variant],
            vocabulary_size=self.vocabulary_size,
            descriptor_length=self.descriptor_length,
            threads=threads,
        )


def load_bundle(path: str | Path, verify_checksums: bool = True) -> ModelBundle:
    """Load and validate a bundle directory; raises BundleError naming what is wrong."""
    path = Path(path)
    if not path.is_dir():
        raise BundleError(f"model bundle {path} does not exist or is not a directory")
    manifest = read_manifest(path)
    files = manifest["files"]
    for name, digest in files.items():
        f = path / name
        if not f.is_file():
            raise BundleError(f"{path}: file {name} listed in the manifest is missing")
        if verify_checksums and sha256_file(f) != digest:
            raise BundleError(f"{path}: checksum mismatch for {name} (file corrupt or modified)")
    v = manifest["vocabulary_size"]
    try:
        features = FeatureConfig.from_dict(manifest["features"])
    except (ConfigError, TypeError) as exc:
        raise BundleError(f"{path}: invalid feature settings in manifest: {exc}") from exc
    if features.descriptor_length != manifest["descriptor_length"]:
        raise BundleError(
            f"{path}: descriptor_length {manifest['descriptor_length']} does not match "
            f"{features.kind} features ({features.descriptor_length})"
        )
    tree_arrays = {k: _load_array(path, n) for k, n in TREE_FILES.items()}
    for k, arr in tree_arrays.items():
        if arr.shape != (v,):
            raise BundleError(f"{path}: tree array {TREE_FILES[k]} has shape {arr.shape}, expected ({v},)")
    try:
        tree = ChowLiuTree(tree_arrays["parent"], tree_arrays["p"], tree_arrays["a"], tree_arrays["b"])
    except InputError as exc:
        raise BundleError(f"{path}: invalid Chow-Liu tree: {exc}") from exc
    indptr = _load_array(path, OBS_FILES["indptr"])
    indices = _load_array(path, OBS_FILES["indices"])
    if indptr.ndim != 1 or indptr.size < 2 or indptr[0] != 0 or indptr[-1] != indices.size or np.any(np.diff(indptr) < 0):
        raise BundleError(f"{path}: training observations index ({OBS_FILES['indptr']}) is inconsistent")
    if indices.size and int(indices.max()) >= v:
        raise BundleError(f"{path}: training observations hold word ids >= vocabulary size {v}")
    indices = indices.astype(np.int64)
    observations = [indices[a:b] for a, b in zip(indptr[:-1], indptr[1:])]
    return ModelBundle(path, manifest, features, tree, observations)


def load_detector(path: str | Path, config=None):
    """A LoopClosureDetector (core) on the bundle at ``path``; config: DetectorConfig or None.

    Raises BundleError from the loader, ConfigError for bad settings.
    """
    from aefabmap.runtime.core.detector import LoopClosureDetector

    return LoopClosureDetector(load_bundle(path), config)


def read_manifest(path: Path) -> dict:
    mpath = path / MANIFEST_NAME
    try:
        manifest = json.loads(mpath.read_text())
    except FileNotFoundError as exc:
        raise BundleError(f"{path}: no {MANIFEST_NAME}; not a model bundle") from exc
    except (OSError, ValueError) as exc:
        raise BundleError(f"{path}: {MANIFEST_NAME} is unreadable or not JSON: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{path}: {MANIFEST_NAME} is not an {BUNDLE_FORMAT} manifest")
    version = manifest.get("format_version")
    if version != BUNDLE_VERSION:
        raise BundleError(f"{path}: bundle format version {version!r} is not supported (this runtime reads {BUNDLE_VERSION})")
    for key in ("features", "descriptor_length", "vocabulary_size", "quantizer", "files"):
        if key not in manifest:
            raise BundleError(f"{path}: manifest lacks required key {key!r}")
    q = manifest["quantizer"]
    if not isinstance(q, dict) or q.get("type") not in QUANTIZER_TYPES or not isinstance(q.get("files"), dict):
        raise BundleError(f"{path}: manifest quantizer must name a type in {QUANTIZER_TYPES} and its files")
    needed = list(TREE_FILES.values()) + list(OBS_FILES.values()) + list(q["files"].values())
    for name in needed:
        if name not in manifest["files"]:
            raise BundleError(f"{path}: manifest has no checksum for {name}")
    if not isinstance(manifest["vocabulary_size"], int) or manifest["vocabulary_size"] < 2:
        raise BundleError(f"{path}: vocabulary_size must be an integer >= 2")
    return manifest


def _load_array(path: Path, name: str) -> np.ndarray:
    try:
        return np.load(path / name, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise BundleError(f"{path}: cannot read array {name}: {exc}") from exc
