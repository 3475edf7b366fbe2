"""Model bundle v1: the one contract between the trainer/aefabmap_trainer/exporter and the runtime.

A bundle is a directory:
    manifest.json                  format, version, features, vocabulary, detector, checksums
    tree_parent.npy  (V,) int32    Chow-Liu parent of each word (root: itself)
    tree_p.npy, tree_a.npy, tree_b.npy  (V,) float64   P(z), P(z|parent), P(z|not parent)
    train_obs_indptr.npy (M+1,) int64, train_obs_indices.npy (nnz,) uint16|uint32
                                   training observations (CSR rows of word ids) for the
                                   sampled new-place model and tf-idf weights
    quantizer files                kmeans: vocabulary.npy (V, D) float32 centroids; optionally an
                                   inverted index (manifest quantizer "index": buckets S, entries
                                   E, distance): index_route_centers.npy (S, D/8) uint8 or (S, D)
                                   float32, index_indptr.npy (S+1,), index_words.npy (E,);
                                   kmeans-tree: vocab_tree_centers.npy (M, W) uint8 packed bits
                                   ("distance": "hamming") or (M, D) float32 ("l2"),
                                   vocab_tree_children.npy (M, B) int32,
                                   vocab_tree_leaf_words.npy (M,) int32; the manifest's
                                   quantizer entry gives "nodes" M and "branching" B;
                                   ae: quantizer_fp32.onnx, quantizer_int8.onnx
    descriptor_weights.npy (256, 256) int8
                                   features "descriptor": "learned" only: the learned ORB
                                   descriptor's projection (manifest "descriptor_weights" names it)
Arrays load with allow_pickle=False. Every file is listed in manifest["files"] with its sha256;
the runtime refuses a bundle whose version, shapes or checksums do not match.

A bundle is untrusted input: only plain files directly inside the bundle directory are read
(no path separators, no "..", no symlinks, no devices or FIFOs), refused before they are
opened; .npy headers are checked (dtype, shape, size on disk) before any array is allocated.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import BundleError, ConfigError, InputError
from aefabmap_runtime.adapters.npy_file import load_npy
from aefabmap_runtime.core.features.features import FeatureConfig
from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES, LearnedDescription
from aefabmap_runtime.core.rank.tree import ChowLiuTree

BUNDLE_FORMAT = "aefabmap-bundle"
BUNDLE_VERSION = 1
MANIFEST_NAME = "manifest.json"
TREE_FILES = {"parent": "tree_parent.npy", "p": "tree_p.npy", "a": "tree_a.npy", "b": "tree_b.npy"}
DESCRIPTOR_WEIGHTS = "descriptor_weights.npy"
OBS_FILES = {"indptr": "train_obs_indptr.npy", "indices": "train_obs_indices.npy"}
QUANTIZER_TYPES = ("kmeans", "kmeans-tree", "ae")
TREE_QUANTIZER_FILES = ("centers", "children", "leaf_words")
#: Files each quantiser type must name in the manifest (role -> file name).
REQUIRED_QUANTIZER_FILES = {"kmeans": ("centroids",), "kmeans-tree": TREE_QUANTIZER_FILES, "ae": ("fp32",)}
#: FAB-MAP's detector model when a manifest has none.
DEFAULT_WORD_DETECTION = {"pzge": 0.39, "pzgne": 0.0}
INDEX_QUANTIZER_FILES = ("index_centers", "index_indptr", "index_words")
#: Bounds of a vocabulary tree's branching factor (children per node).
MAX_TREE_BRANCHING = 256


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        _update_hash(h, fh)
    return h.hexdigest()


def _update_hash(h, fh) -> None:
    for block in iter(lambda: fh.read(1 << 20), b""):
        h.update(block)


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
    #: The learned descriptor's projection (features.descriptor "learned"), else None.
    learned_description: LearnedDescription | None = field(default=None, repr=False)

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
    def word_detection(self) -> dict:
        """FAB-MAP's detector model of the manifest: {"pzge": P(z=1 | e=1), "pzgne": P(z=1 | e=0)}."""
        return dict(self.manifest.get("detector", DEFAULT_WORD_DETECTION))

    def quantizer(self, variant: str = "fp32", threads: int = 1):
        """Build the bundle's quantiser (Quantizer protocol).

        variant: "fp32" | "int8" (ae); a k-means bundle with an inverted index uses it unless
        variant is "flat" (the exhaustive arg-min over the same words). The flat search of a
        binary kind runs as an int8 product with an exact re-rank (BitCentroidQuantizer: the same
        words); "flat-fp32" forces the float32 product (NearestCentroidQuantizer).
        """
        q = self.manifest["quantizer"]
        files = q["files"]
        if self.quantizer_type == "kmeans":
            from aefabmap_runtime.core.words.bit_centroids import flat_quantizer

            name = files["centroids"]
            centroids = _load_array(
                self.path, name, kinds="f", shape=(self.vocabulary_size, self.descriptor_length)
            )
            if not np.isfinite(centroids).all():
                raise BundleError(f"{self.path}: {name} holds NaN or infinite centroids")
            if "index" in q and variant not in ("flat", "flat-fp32"):
                return self._indexed(centroids)
            return flat_quantizer(centroids, self.features.spec.distance, float32=variant == "flat-fp32",
                                  threads=threads)
        if self.quantizer_type == "kmeans-tree":
            return self._vocabulary_tree()
        if variant not in files:
            raise ConfigError(f"bundle {self.path} has no {variant!r} quantiser; it has {sorted(files)}")
        from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer

        return OnnxQuantizer(
            self.path / files[variant],
            vocabulary_size=self.vocabulary_size,
            descriptor_length=self.descriptor_length,
            threads=threads,
        )


    def _indexed(self, centroids: np.ndarray):
        """The flat vocabulary with its inverted index; shapes from the manifest, checked in the
        .npy headers before loading, then the lists (validate_index)."""
        from aefabmap_runtime.core.words.quantizer import IndexedCentroidQuantizer

        q, v = self.manifest["quantizer"], self.vocabulary_size
        index, files = q["index"], q["files"]
        if not isinstance(index, dict) or not all(k in files for k in INDEX_QUANTIZER_FILES):
            raise BundleError(f"{self.path}: a k-means index names the files {INDEX_QUANTIZER_FILES}")
        s, n, distance = index.get("buckets"), index.get("entries"), index.get("distance")
        if not _is_int(s) or not 1 <= s <= v:
            raise BundleError(f"{self.path}: index 'buckets' must be an integer in [1, {v}]")
        if not _is_int(n) or not v <= n <= s * v:
            raise BundleError(f"{self.path}: index 'entries' must be an integer in [{v}, {s * v}]")
        centers = self._centres(files["index_centers"], s, distance, "index")
        indptr = _load_array(self.path, files["index_indptr"], kinds="iu", shape=(s + 1,))
        words = _load_array(self.path, files["index_words"], kinds="iu", shape=(n,))
        try:
            return IndexedCentroidQuantizer(np.asarray(centroids, np.float32), centers, indptr, words)
        except InputError as exc:
            raise BundleError(f"{self.path}: invalid vocabulary index: {exc}") from exc

    def _centres(self, name: str, rows: int, distance, what: str) -> np.ndarray:
        """Routing centres (rows, D // 8) uint8 for Hamming or (rows, D) float32 for L2, as the
        manifest's `distance` says; header checked before loading (index and tree alike)."""
        d = self.descriptor_length
        if distance == "hamming":
            if self.features.spec.distance != "hamming" or d % 8:
                raise BundleError(f"{self.path}: Hamming {what} centres need a binary feature kind")
            centers, want = _load_array(self.path, name, kinds="u", shape=(rows, d // 8)), np.uint8
        elif distance == "l2":
            centers, want = _load_array(self.path, name, kinds="f", shape=(rows, d)), np.float32
        else:
            raise BundleError(f"{self.path}: {what} 'distance' must be 'hamming' or 'l2', got {str(distance)[:40]!r}")
        if centers.dtype != want:
            raise BundleError(f"{self.path}: {name} must hold {np.dtype(want)}, got {centers.dtype}")
        return centers

    def _vocabulary_tree(self):
        """The kmeans-tree quantiser; shapes come from the manifest and are checked in each
        .npy header before loading, then the tree's structure (VocabularyTree validation)."""
        from aefabmap_runtime.core.words.vocab_tree import VocabularyTree

        q = self.manifest["quantizer"]
        files, v = q["files"], self.vocabulary_size
        if set(files) != set(TREE_QUANTIZER_FILES):
            raise BundleError(f"{self.path}: a kmeans-tree quantizer names the files {TREE_QUANTIZER_FILES}")
        m, b, distance = q.get("nodes"), q.get("branching"), q.get("distance")
        # Every inner node has >= 2 children: at most 2 V - 1 nodes.
        if not _is_int(m) or not 3 <= m <= 2 * v - 1:
            raise BundleError(f"{self.path}: kmeans-tree 'nodes' must be an integer in [3, {2 * v - 1}]")
        if not _is_int(b) or not 2 <= b <= min(MAX_TREE_BRANCHING, v):
            raise BundleError(f"{self.path}: kmeans-tree 'branching' must be an integer in [2, {min(MAX_TREE_BRANCHING, v)}]")
        centers = self._centres(files["centers"], m, distance, "kmeans-tree")
        children = _load_array(self.path, files["children"], kinds="i", shape=(m, b))
        leaf_words = _load_array(self.path, files["leaf_words"], kinds="i", shape=(m,))
        try:
            tree = VocabularyTree(centers, children, leaf_words)
        except InputError as exc:
            raise BundleError(f"{self.path}: invalid vocabulary tree: {exc}") from exc
        if tree.vocabulary_size != v:
            raise BundleError(f"{self.path}: vocabulary tree has {tree.vocabulary_size} leaves, manifest says {v} words")
        return tree


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def load_bundle(path: str | Path, verify_checksums: bool = True) -> ModelBundle:
    """Load and validate a bundle directory; raises BundleError naming what is wrong."""
    path = Path(path)
    if not path.is_dir():
        raise BundleError(f"model bundle {path} does not exist or is not a directory")
    manifest = read_manifest(path)
    files = manifest["files"]
    for name in files:
        _check_file_name(path, name)
    for name, digest in files.items():
        with _open_bundle_file(path, name) as fh:
            if verify_checksums:
                h = hashlib.sha256()
                _update_hash(h, fh)
                if h.hexdigest() != digest:
                    raise BundleError(f"{path}: checksum mismatch for {name} (file corrupt or modified)")
    v = manifest["vocabulary_size"]
    try:
        if not isinstance(manifest["features"], dict):
            raise ConfigError("'features' must be an object")
        features = FeatureConfig.from_dict(manifest["features"])
    except (ConfigError, TypeError) as exc:
        raise BundleError(f"{path}: invalid feature settings in manifest: {exc}") from exc
    if features.descriptor_length != manifest["descriptor_length"]:
        raise BundleError(
            f"{path}: descriptor_length {manifest['descriptor_length']} does not match "
            f"{features.kind} features ({features.descriptor_length})"
        )
    tree_arrays = {
        k: _load_array(path, n, kinds="iu" if k == "parent" else "f", shape=(v,)) for k, n in TREE_FILES.items()
    }
    try:
        tree = ChowLiuTree(tree_arrays["parent"], tree_arrays["p"], tree_arrays["a"], tree_arrays["b"])
    except InputError as exc:
        raise BundleError(f"{path}: invalid Chow-Liu tree: {exc}") from exc
    indptr = _load_array(path, OBS_FILES["indptr"], kinds="iu", shape=(None,))
    indices = _load_array(path, OBS_FILES["indices"], kinds="iu", shape=(None,))
    if indptr.size < 2 or indptr[0] != 0 or indptr[-1] != indices.size or np.any(np.diff(indptr) < 0):
        raise BundleError(f"{path}: training observations index ({OBS_FILES['indptr']}) is inconsistent")
    if indices.size and (int(indices.min()) < 0 or int(indices.max()) >= v):
        raise BundleError(
            f"{path}: {OBS_FILES['indices']} holds word ids outside [0, {v}) (vocabulary size {v})"
        )
    indices = indices.astype(np.int64)
    observations = [indices[a:b] for a, b in zip(indptr[:-1], indptr[1:])]
    return ModelBundle(path, manifest, features, tree, observations, _learned_description(path, manifest, features))


def _learned_description(path: Path, manifest: dict, features: FeatureConfig) -> LearnedDescription | None:
    """The learned descriptor's projection a "learned" bundle names (header checked first)."""
    name = manifest.get("descriptor_weights")
    if features.descriptor != "learned":
        if name is not None:
            raise BundleError(f"{path}: 'descriptor_weights' belongs to features with descriptor 'learned'")
        return None
    if not isinstance(name, str) or name not in manifest["files"]:
        raise BundleError(f"{path}: a learned descriptor needs 'descriptor_weights' naming a checksummed file")
    weights = _load_array(path, name, kinds="i", shape=(BITS, SAMPLES))
    try:  # LearnedDescription refuses weights that are not int8 or all zero
        return LearnedDescription(weights)
    except InputError as exc:
        raise BundleError(f"{path}: invalid learned descriptor: {exc}") from exc


def load_detector(path: str | Path, config=None):
    """A LoopClosureDetector (core) on the bundle at ``path``; config: DetectorConfig or None.

    Raises BundleError from the loader, ConfigError for bad settings.
    """
    from aefabmap_runtime.core.detector import LoopClosureDetector

    return LoopClosureDetector(load_bundle(path), config)


def read_manifest(path: Path) -> dict:
    if not (path / MANIFEST_NAME).exists() and not (path / MANIFEST_NAME).is_symlink():
        raise BundleError(f"{path}: no {MANIFEST_NAME}; not a model bundle")
    try:
        with _open_bundle_file(path, MANIFEST_NAME) as fh:
            if os.fstat(fh.fileno()).st_size > MAX_MANIFEST_BYTES:
                raise BundleError(f"{path}: {MANIFEST_NAME} is larger than {MAX_MANIFEST_BYTES} bytes")
            manifest = json.loads(fh.read())
    except (OSError, ValueError, RecursionError) as exc:
        raise BundleError(f"{path}: {MANIFEST_NAME} is unreadable or not JSON: {exc}") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{path}: {MANIFEST_NAME} is not an {BUNDLE_FORMAT} manifest")
    version = manifest.get("format_version")
    if version != BUNDLE_VERSION:
        raise BundleError(f"{path}: bundle format version {version!r} is not supported (this runtime reads {BUNDLE_VERSION})")
    for key in ("features", "descriptor_length", "vocabulary_size", "quantizer", "files"):
        if key not in manifest:
            raise BundleError(f"{path}: manifest lacks required key {key!r}")
    if not isinstance(manifest["files"], dict) or not all(
        isinstance(k, str) and isinstance(d, str) for k, d in manifest["files"].items()
    ):
        raise BundleError(f"{path}: manifest files must map file names to sha256 strings")
    q = manifest["quantizer"]
    if (
        not isinstance(q, dict)
        or q.get("type") not in QUANTIZER_TYPES
        or not isinstance(q.get("files"), dict)
        or not all(isinstance(n, str) for n in q["files"].values())
    ):
        raise BundleError(f"{path}: manifest quantizer must name a type in {QUANTIZER_TYPES} and its files")
    needed = list(TREE_FILES.values()) + list(OBS_FILES.values()) + list(q["files"].values())
    for name in needed:
        if name not in manifest["files"]:
            raise BundleError(f"{path}: manifest has no checksum for {name}")
    if not isinstance(manifest["vocabulary_size"], int) or manifest["vocabulary_size"] < 2:
        raise BundleError(f"{path}: vocabulary_size must be an integer >= 2")
    missing = [role for role in REQUIRED_QUANTIZER_FILES[q["type"]] if role not in q["files"]]
    if missing:
        raise BundleError(f"{path}: a {q['type']} quantizer names the files {REQUIRED_QUANTIZER_FILES[q['type']]}; "
                          f"the manifest lacks {', '.join(missing)}")
    _check_word_detection(path, manifest.get("detector", DEFAULT_WORD_DETECTION))
    return manifest


def _check_word_detection(path: Path, det: object) -> None:
    """FAB-MAP's detector model of the manifest: {"pzge": p, "pzgne": q}, 0 <= q < p <= 1."""
    if not isinstance(det, dict) or set(det) != {"pzge", "pzgne"}:
        raise BundleError(f"{path}: manifest 'detector' must be an object with exactly pzge and pzgne")
    p, q = det["pzge"], det["pzgne"]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (p, q)) \
            or not (0.0 <= q < p <= 1.0):  # NaN fails the comparison too
        raise BundleError(f"{path}: manifest 'detector' needs numbers 0 <= pzgne < pzge <= 1, "
                          f"got pzge={str(p)[:20]}, pzgne={str(q)[:20]}")


#: A manifest is a few kB; refuse to parse anything much larger.
MAX_MANIFEST_BYTES = 1 << 20


def _check_file_name(path: Path, name) -> None:
    """Refuse a manifest file name that is not a plain name of a file inside the bundle.

    Checked on the name alone, before any file-system access, so a refusal says nothing
    about what exists outside the bundle.
    """
    plain = (
        isinstance(name, str)
        and name not in ("", ".", "..")
        and not any(c in name for c in ("/", "\\", "\x00"))
        and os.path.basename(name) == name
    )
    if not plain:
        raise BundleError(f"{path}: manifest names {str(name)[:100]!r}, which is not a plain file name inside the bundle")


def _open_bundle_file(path: Path, name: str):
    """Open ``path / name`` for reading in binary mode; it must be a regular file (no symlink,
    FIFO or device: O_NOFOLLOW | O_NONBLOCK, then fstat), else BundleError."""
    _check_file_name(path, name)
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path / name, flags)
    except FileNotFoundError:
        raise BundleError(f"{path}: file {name} listed in the manifest is missing") from None
    except OSError as exc:  # ELOOP: a symlink under O_NOFOLLOW
        raise BundleError(f"{path}: {name} is not a regular file of the bundle ({exc.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise BundleError(f"{path}: {name} is not a regular file of the bundle")
    return os.fdopen(fd, "rb")


def _load_array(path: Path, name: str, *, kinds: str = "biuf", shape: tuple | None = None) -> np.ndarray:
    """Load ``path / name`` (.npy), a regular file of the bundle, after checking its header.

    kinds / shape: see :func:`npy_file.load_npy` (None entries of shape match any length).
    """
    with _open_bundle_file(path, name) as fh:
        return load_npy(fh, f"{path}: array {name}", kinds=kinds, shape=shape, error=BundleError)
