"""Training pipeline: images -> features -> vocabulary -> observations -> Chow-Liu -> bundle."""

from __future__ import annotations

import hashlib
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from aefabmap_runtime.errors import ConfigError, DataNotFoundError, InputError
from aefabmap_export.bundle_writer import write_bundle
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.adapters.image_folder import IMAGE_SUFFIXES
from aefabmap_runtime.core.features.feature_kinds import FeatureKind
from aefabmap_runtime.core.features.features import EXTRACTION_VERSION, FeatureConfig, FeatureExtractor
from aefabmap_runtime.core.features.learned_description import LearnedDescription
from aefabmap_runtime.core.words.quantizer import quantize_raw
from aefabmap_trainer.ae_quantizer import OBJECTIVES
from aefabmap_trainer.assign_objective import ASSIGN_INITS
from aefabmap_trainer.chow_liu import fit_chow_liu
from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans
from aefabmap_trainer.learned_descriptor import DescriptorTraining, train_learned_description

QUANTIZERS = ("kmeans", "kmeans-tree", "ae")


@dataclass(frozen=True)
class TrainConfig:
    """What `aefabmap train` learns.

    images: training image directories (searched recursively, sorted by path).
    words: vocabulary size K. max_descriptors: descriptors sampled for clustering (quantizer "ae":
        at least ae_descriptors).
    quantizer: "kmeans" (flat vocabulary), "kmeans-tree" (vocabulary tree with `branching`
        children per node, exactly `words` leaves; binary kinds get k-majority bit centres
        compared by popcount unless float_centers) or "ae".
    index_buckets: quantizer "kmeans" only: 0 (default) searches the flat vocabulary exhaustively;
        S > 0 adds an inverted index of S buckets (IndexedCentroidQuantizer: the flat words, a
        descriptor compared only with its bucket's list; on ORB 3000 words with S = 32 the search
        is not faster: docs/results.md, "Quantisation in O(log K): flat search, vocabulary tree,
        inverted index").
    vocabulary_from: quantizer "kmeans" only: take the centroids of this k-means bundle (same
        feature settings) instead of clustering again (e.g. to add an index to it).
    ae_epochs / ae_descriptors: autoencoder training budget (quantizer "ae" only).
    ae_arch / ae_latent: "paper" conv stack or "light" MLP; latent size (None: the arch's default).
    ae_patience / ae_budget_s: early-stopping patience (epochs) and wall-clock training budget.
    ae_learning_rate: the AE's Adam learning rate.
    ae_threads: torch and onnxruntime threads of the AE stages (on a loaded machine 1 thread
        trains far faster than 2 that keep waiting for each other; docs/results.md,
        "Autoencoder vs k-means").
    ae_match_weight: weight of the matching term on latent codes (0: reconstruction only).
    ae_warp_images / ae_frame_pairs: sources of matching pairs (synthetic homography warps of
        training images; consecutive frames of the drives among them), built whenever either is
        > 0: they train the matching term and give the held-out pair word agreement.
    ae_objective: "recon" (reconstruction [+ matching term], then k-means on the codes) or "assign"
        (encoder and words trained so that views of one scene point share a word,
        trainer/aefabmap_trainer/assign_objective.py; light arch only). The AE defaults (assign, light, 6 views,
        reconstruction weight 1, 8 epochs) are the best AE measured (docs/results.md, "The
        word-assignment objective"); the paper's conv stack is ae_objective "recon" with
        ae_arch "paper".
    ae_views / ae_track_images: objective "assign": views per scene point (the image and
        ae_views - 1 warped, photometrically changed copies; a point is kept when seen in >= 3)
        and how many training images (outside the test split) give tracks.
    ae_light_views: objective "assign": how many of those copies are the unwarped image at a
        random night instead (trainer/aefabmap_trainer/multiview.build_tracks), < ae_views.
    ae_balance_weight / ae_recon_weight: objective "assign": weights of the word-usage and
        reconstruction terms.
    ae_temperature_end: objective "assign": the soft assignment's final temperature, in codebook
        spacings (AssignConfig.temperature_end).
    ae_init: objective "assign": "random" encoder, or "kmeans" (the encoder starts as the
        projection onto the descriptors' principal axes, the words as k-means of it,
        assign_objective.init_linear_pca).
    cache_dir: where extracted training features are kept between runs (None: no cache);
        entries are keyed by the feature settings and the image list, so a stale entry is
        never reused.
    descriptor_training: features.descriptor "learned": how the descriptor is trained first
        (trainer/aefabmap_trainer/learned_descriptor.py).
    """

    images: tuple[Path, ...]
    out: Path
    features: FeatureConfig = field(default_factory=FeatureConfig)
    quantizer: str = "kmeans"
    words: int = 2000
    branching: int = 10
    index_buckets: int = 0
    vocabulary_from: Path | None = None
    float_centers: bool = False
    seed: int = 0
    max_descriptors: int = 200_000
    kmeans_iterations: int = 25
    ae_epochs: int = 8
    ae_descriptors: int = 250_000
    ae_arch: str = "light"
    ae_latent: int | None = None
    ae_patience: int = 2
    ae_budget_s: float | None = None
    ae_learning_rate: float = 2e-3
    ae_match_weight: float = 0.0
    ae_warp_images: int = 0
    ae_frame_pairs: int = 0
    ae_threads: int = 1
    ae_match_negatives: str = "batch"
    ae_objective: str = "assign"
    ae_views: int = 6
    ae_track_images: int = 1500
    ae_light_views: int = 0
    ae_balance_weight: float = 1.0
    ae_recon_weight: float = 1.0
    ae_temperature_end: float = 0.3
    ae_init: str = "random"
    cache_dir: Path | None = None
    descriptor_training: DescriptorTraining = field(default_factory=DescriptorTraining)
    show_progress: bool = True

    def __post_init__(self) -> None:
        if self.quantizer not in QUANTIZERS:
            raise ConfigError(f"quantizer must be one of {QUANTIZERS}, got {self.quantizer!r}")
        if self.words < 2:
            raise ConfigError(f"--words must be >= 2, got {self.words}")
        if not 2 <= self.branching <= 256:
            raise ConfigError(f"--branching must be in [2, 256], got {self.branching}")
        if self.index_buckets < 0 or self.index_buckets > self.words:
            raise ConfigError(f"--index-buckets must be in [0, words], got {self.index_buckets}")
        if (self.index_buckets or self.vocabulary_from) and self.quantizer != "kmeans":
            raise ConfigError("--index-buckets and --vocabulary-from apply to --quantizer kmeans")
        if self.max_descriptors < self.words:
            raise ConfigError(f"max_descriptors ({self.max_descriptors}) must be >= words ({self.words})")
        if self.ae_objective not in OBJECTIVES:
            raise ConfigError(f"--ae-objective must be one of {OBJECTIVES}, got {self.ae_objective!r}")
        if self.ae_objective == "assign" and (self.ae_arch != "light" or self.ae_views < 3 or self.ae_track_images < 2):
            raise ConfigError("--ae-objective assign needs --ae-arch light, --ae-views >= 3 and --ae-track-images >= 2")
        if not 0 <= self.ae_light_views < self.ae_views:
            raise ConfigError(f"--ae-light-views must be >= 0 and below --ae-views ({self.ae_views}), got {self.ae_light_views}")
        if not (math.isfinite(self.ae_temperature_end) and self.ae_temperature_end > 0):
            raise ConfigError(f"--ae-temperature-end must be a finite number > 0, got {self.ae_temperature_end}")
        if self.features.descriptor == "learned" and self.quantizer == "ae":
            raise ConfigError("--descriptor learned trains k-means vocabularies (--quantizer kmeans or kmeans-tree)")
        if self.ae_init not in ASSIGN_INITS or (self.ae_init != "random" and self.ae_objective != "assign"):
            raise ConfigError(f"--ae-init must be one of {ASSIGN_INITS} (with --ae-objective assign), got {self.ae_init!r}")


def find_training_images(dirs) -> list[Path]:
    """All image files under the given directories, recursively, in sorted path order."""
    files: list[Path] = []
    for d in dirs:
        d = Path(d)
        if not d.is_dir():
            raise DataNotFoundError(f"training image directory {d} does not exist")
        found = sorted(p for p in d.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        if not found:
            raise DataNotFoundError(f"no training images under {d}")
        files.extend(found)
    return files


def extract_training_vectors(files: list[Path], features: FeatureConfig, show_progress: bool = True,
                             learned: LearnedDescription | None = None) -> list[np.ndarray]:
    """Raw descriptors (n_i, width) of every training image (unreadable images are an error).

    Kept in the kind's raw form (binary kinds stay packed: 32 bytes for ORB instead of 1 KiB of
    float bits) and turned into descriptor vectors per use (`FeatureKind.vectors`).
    """
    extractor = FeatureExtractor(features, learned=learned)
    return [
        extractor.extract(load_image(f)).descriptors
        for f in tqdm(files, desc="features", disable=not show_progress, mininterval=1.0)
    ]


def cache_entry(cache_dir: Path, prefix: str, features: FeatureConfig, files: list[Path], settings: str = "") -> Path:
    """The .npz cache entry of `prefix` data built from `files` with these feature settings and
    further `settings`: keyed by both and by each image's path, size and modification time, so a
    stale entry is never reused (nor one written by an extractor of another EXTRACTION_VERSION)."""
    text = (f"extraction {EXTRACTION_VERSION}\n" + repr(sorted(features.to_dict().items()))
            + (f"\n{settings}\n" if settings else "\n")
            + "\n".join(f"{f}:{f.stat().st_size}:{f.stat().st_mtime_ns}" for f in files))
    return Path(cache_dir) / f"{prefix}-{features.kind}-{hashlib.sha256(text.encode()).hexdigest()[:20]}.npz"


def read_cache_entry(entry: Path, names: tuple[str, ...]) -> dict[str, np.ndarray] | None:
    """The named arrays of a cache entry, or None when it is missing or unreadable (then built
    again; callers also rebuild an entry whose arrays do not fit together)."""
    if not entry.is_file():
        return None
    try:
        with np.load(entry, allow_pickle=False) as z:
            return {n: z[n] for n in names}
    except (OSError, ValueError, KeyError):
        return None


def write_cache_entry(entry: Path, **arrays: np.ndarray) -> None:
    """Write arrays to the .npz cache entry `entry` atomically: through a temporary file of this
    writer's own, so that trainings sharing a cache directory never rename each other's files."""
    entry.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=entry.parent, prefix=entry.stem + ".", suffix=".tmp.npz")
    tmp = Path(name)
    try:
        with open(fd, "wb") as f:
            np.savez(f, **arrays)
        tmp.replace(entry)
    finally:
        tmp.unlink(missing_ok=True)


def cached_training_vectors(files: list[Path], features: FeatureConfig, cache_dir: Path | None, show_progress: bool,
                            learned: LearnedDescription | None = None) -> list[np.ndarray]:
    """extract_training_vectors, reusing a cache entry for the same settings, projection and images."""
    if cache_dir is None:
        return extract_training_vectors(files, features, show_progress, learned)
    weights = "" if learned is None else "learned " + hashlib.sha256(learned.weights.tobytes()).hexdigest()
    entry = cache_entry(cache_dir, "features", features, files, weights)
    cached = read_cache_entry(entry, ("descriptors", "counts"))
    if cached is not None:
        flat, counts = cached["descriptors"], cached["counts"]
        if counts.size == len(files) and counts.sum() == flat.shape[0]:
            return np.split(flat, np.cumsum(counts)[:-1])
    per_image = extract_training_vectors(files, features, show_progress, learned)
    flat = np.concatenate(per_image) if per_image else features.spec.empty()
    write_cache_entry(entry, descriptors=flat, counts=np.array([len(a) for a in per_image]))
    return per_image


def cached_match_pairs(files: list[Path], features: FeatureConfig, cache_dir: Path | None, *, warp_images: int,
                       frame_pairs: int, seed: int, show_progress: bool):
    """trainer.match_pairs.build_match_pairs, reusing a cache entry for the same settings and images."""
    from aefabmap_trainer.match_pairs import MatchPairs, build_match_pairs

    entry = None
    if cache_dir is not None:
        entry = cache_entry(cache_dir, "pairs", features, files, f"{warp_images}:{frame_pairs}:{seed}")
        cached = read_cache_entry(entry, ("a", "b", "group"))
        if cached is not None and cached["a"].ndim == 2 and cached["a"].shape == cached["b"].shape \
                and cached["group"].shape == cached["a"].shape[:1]:
            return MatchPairs(**cached)
    pairs = build_match_pairs(files, FeatureExtractor(features), warp_images=warp_images, frame_pairs=frame_pairs,
                              seed=seed, progress=show_progress)
    if entry is not None:
        write_cache_entry(entry, a=pairs.a, b=pairs.b, group=pairs.group)
    return pairs


def cached_tracks(files: list[Path], features: FeatureConfig, cache_dir: Path | None, *, images: int, views: int,
                  seed: int, show_progress: bool, light_views: int = 0):
    """trainer.multiview.build_tracks, reusing a cache entry for the same settings and images."""
    from aefabmap_trainer.multiview import Tracks, build_tracks

    entry = None
    if cache_dir is not None:
        light = f":light{light_views}" if light_views else ""  # entries made before the option keep their key
        entry = cache_entry(cache_dir, "tracks", features, files, f"tracks:{images}:{views}:{seed}{light}")
        cached = read_cache_entry(entry, ("x", "mask", "group"))
        if cached is not None and cached["x"].ndim == 3 and cached["mask"].shape == cached["x"].shape[:2] \
                and cached["mask"].dtype == bool and cached["group"].shape == cached["x"].shape[:1]:
            return Tracks(**cached)
    tracks = build_tracks(files, FeatureExtractor(features), images=images, views=views, seed=seed,
                          light_views=light_views, progress=show_progress)
    if entry is not None:
        write_cache_entry(entry, x=tracks.x, mask=tracks.mask, group=tracks.group)
    return tracks


def sample_vectors(per_image: list[np.ndarray], kind: FeatureKind, n: int, seed: int) -> np.ndarray:
    """Up to n descriptor vectors (the kind's vector form) drawn uniformly (seeded) from all training images."""
    counts = np.array([len(a) for a in per_image])
    total = int(counts.sum())
    if total == 0:
        raise InputError("no descriptors were found in the training images")
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(total, size=min(n, total), replace=False))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    img = np.searchsorted(offsets, pick, side="right") - 1
    rows = [per_image[i][k - offsets[i]] for i, k in zip(img.tolist(), pick.tolist())]
    return kind.vectors(np.stack(rows))


@dataclass
class TrainResult:
    path: Path
    summary: dict
    timings_s: dict


def train_bundle(config: TrainConfig) -> TrainResult:
    """Run the whole training pipeline and write the bundle."""
    t_start = time.perf_counter()
    timings = {}
    files = find_training_images(config.images)
    kind = config.features.spec
    learned, descriptor_pairs = None, 0
    if config.features.descriptor == "learned":
        t0 = time.perf_counter()
        learned, descriptor_pairs = train_learned_description(files, config.features, config.descriptor_training,
                                                              config.show_progress)
        timings["descriptor_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    per_image = cached_training_vectors(files, config.features, config.cache_dir, config.show_progress, learned)
    timings["features_s"] = time.perf_counter() - t0
    # The AE trains on ae_descriptors of the sample, so its sample holds at least that many.
    n_sample = max(config.max_descriptors, config.ae_descriptors) if config.quantizer == "ae" else config.max_descriptors
    sample = sample_vectors(per_image, kind, n_sample, config.seed)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        if config.quantizer == "kmeans":
            bar = tqdm(total=config.kmeans_iterations, desc="k-means",
                       disable=not config.show_progress or config.vocabulary_from is not None)

            def tick(it, moved):
                bar.update(1)
                bar.set_postfix(moved=f"{moved:.4f}")

            if config.vocabulary_from is not None:
                centroids, clustered = _centroids_from(config)
            else:
                centroids = fit_kmeans(sample, config.words, KMeansConfig(config.kmeans_iterations, seed=config.seed), tick)
                clustered = int(sample.shape[0])
            bar.close()
            from aefabmap_runtime.core.words.bit_centroids import flat_quantizer

            # The runtime's own flat search, so that training words are the words it will give.
            quantizer = flat_quantizer(centroids, kind.distance)
            q_manifest = {"type": "kmeans", "files": {"centroids": "vocabulary.npy"}, "descriptors_clustered": clustered}
            q_files: dict = {"vocabulary.npy": centroids}
            if config.index_buckets:
                quantizer, index_manifest, index_files, observations = _train_index(sample, per_image, kind, quantizer, config)
                q_manifest["files"] |= index_manifest.pop("files")
                q_manifest["index"] = index_manifest
                q_files |= index_files
        elif config.quantizer == "kmeans-tree":
            quantizer, q_manifest, q_files = _train_tree(sample, kind, config)
        else:
            from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer
            from aefabmap_trainer.ae_quantizer import build_ae_quantizer
            from aefabmap_trainer.autoencoder import AeConfig

            pairs = None
            if config.ae_warp_images > 0 or config.ae_frame_pairs > 0:
                t1 = time.perf_counter()
                pairs = cached_match_pairs(files, config.features, config.cache_dir, warp_images=config.ae_warp_images,
                                           frame_pairs=config.ae_frame_pairs, seed=config.seed,
                                           show_progress=config.show_progress)
                timings["match_pairs_s"] = time.perf_counter() - t1
            tracks = assign = None
            if config.ae_objective == "assign":
                from aefabmap_trainer.assign_objective import AssignConfig

                t1 = time.perf_counter()
                tracks = cached_tracks(files, config.features, config.cache_dir, images=config.ae_track_images,
                                       views=config.ae_views, seed=config.seed, show_progress=config.show_progress,
                                       light_views=config.ae_light_views)
                timings["tracks_s"] = time.perf_counter() - t1
                # A k-means start clusters as the k-means quantiser does; a random one keeps AssignConfig's count.
                start = {"init_kmeans_iterations": config.kmeans_iterations} if config.ae_init == "kmeans" else {}
                assign = AssignConfig(balance_weight=config.ae_balance_weight, recon_weight=config.ae_recon_weight,
                                      temperature_end=config.ae_temperature_end, init=config.ae_init, **start)
            q_manifest = build_ae_quantizer(
                sample,
                words=config.words,
                seed=config.seed,
                feature_kind=kind.name,
                out_dir=Path(work),
                config=AeConfig(
                    arch=config.ae_arch,
                    latent_dim=config.ae_latent,
                    max_epochs=config.ae_epochs,
                    max_descriptors=config.ae_descriptors,
                    patience=config.ae_patience,
                    max_seconds=config.ae_budget_s,
                    learning_rate=config.ae_learning_rate,
                    match_weight=config.ae_match_weight,
                    match_negatives=config.ae_match_negatives,
                    threads=config.ae_threads,
                    progress=config.show_progress,
                ),
                pairs=pairs,
                objective=config.ae_objective,
                tracks=tracks,
                assign=assign,
            )
            # Wall-clock times go to the printed timings, not into the bundle: same command, same bytes.
            timings.update({f"ae_{k}": v for k, v in q_manifest.pop("timings").items()})
            q_files = {name: Path(work) / name for name in q_manifest["files"].values()}
            quantizer = OnnxQuantizer(
                Path(work) / q_manifest["files"]["fp32"],
                vocabulary_size=config.words,
                descriptor_length=config.features.descriptor_length,
                threads=config.ae_threads,
            )
        timings["vocabulary_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if not (config.quantizer == "kmeans" and config.index_buckets):  # the index pass made them
            observations = [
                np.unique(quantize_raw(quantizer, kind, raw)) if len(raw) else np.zeros(0, np.int64)
                for raw in tqdm(per_image, desc="quantise", disable=not config.show_progress, mininterval=1.0)
            ]
        timings["quantise_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        tree = fit_chow_liu(observations, config.words)
        timings["chow_liu_s"] = time.perf_counter() - t0
        summary = {
            "image_dirs": [Path(d).name for d in config.images],
            "images": len(files),
            "image_names_sha256": hashlib.sha256("\n".join(f.name for f in files).encode()).hexdigest(),
            "descriptors": int(sum(len(a) for a in per_image)),
            "mean_words_per_image": float(np.mean([o.size for o in observations])),
            "seed": config.seed,
            "quantizer": config.quantizer,
            "words": config.words,
        }
        if config.quantizer == "ae" and config.ae_objective == "assign":  # the views it was trained on
            summary |= {"ae_views": config.ae_views, "ae_light_views": config.ae_light_views,
                        "ae_track_images": config.ae_track_images}
        if config.index_buckets:
            summary |= {"index_buckets": config.index_buckets, "index_entries": int(quantizer.words.size)}
        if config.vocabulary_from is not None:
            summary["vocabulary_from"] = Path(config.vocabulary_from).name
        if config.quantizer == "kmeans-tree":
            summary |= {"branching": config.branching, "tree_depth": quantizer.depth, "tree_nodes": quantizer.nodes}
        if learned is not None:
            d = config.descriptor_training
            summary |= {"descriptor_images": d.images, "descriptor_epochs": d.epochs, "descriptor_warp": d.warp,
                        "descriptor_pairs": descriptor_pairs}
        out = write_bundle(
            config.out,
            features=config.features,
            tree=tree,
            training_observations=observations,
            quantizer=q_manifest,
            quantizer_files=q_files,
            training_summary=summary,
            learned=learned,
        )
    timings["total_s"] = time.perf_counter() - t_start
    return TrainResult(out, summary, timings)


#: Bundle file names of the vocabulary tree's arrays (runtime/aefabmap_runtime/adapters/bundle_reader.py).
TREE_FILE_NAMES = {
    "centers": "vocab_tree_centers.npy",
    "children": "vocab_tree_children.npy",
    "leaf_words": "vocab_tree_leaf_words.npy",
}


def _train_tree(sample: np.ndarray, kind: FeatureKind, config: TrainConfig):
    """The vocabulary tree of `sample`: (quantiser, manifest entry, bundle files)."""
    from aefabmap_runtime.core.words.vocab_tree import VocabularyTree
    from aefabmap_trainer.hierarchical_kmeans import fit_vocab_tree

    binary = kind.distance == "hamming" and not config.float_centers
    bar = tqdm(desc="tree nodes", disable=not config.show_progress, mininterval=1.0)
    arrays = fit_vocab_tree(
        sample, config.words, config.branching, binary=binary,
        config=KMeansConfig(config.kmeans_iterations, seed=config.seed), progress=lambda node: bar.update(1),
    )
    bar.close()
    if arrays.words != config.words:
        raise InputError(f"the training descriptors have too few distinct rows for {config.words} tree leaves "
                         f"(got {arrays.words})")
    quantizer = VocabularyTree(arrays.centers, arrays.children, arrays.leaf_words)
    manifest = {
        "type": "kmeans-tree",
        "files": dict(TREE_FILE_NAMES),
        "branching": config.branching,
        "nodes": quantizer.nodes,
        "depth": quantizer.depth,
        "distance": "hamming" if binary else "l2",
        "descriptors_clustered": int(sample.shape[0]),
    }
    files = {
        TREE_FILE_NAMES["centers"]: arrays.centers,
        TREE_FILE_NAMES["children"]: arrays.children,
        TREE_FILE_NAMES["leaf_words"]: arrays.leaf_words,
    }
    return quantizer, manifest, files


#: Bundle file names of the flat vocabulary's inverted index (runtime/aefabmap_runtime/adapters/bundle_reader.py).
INDEX_FILE_NAMES = {
    "index_centers": "index_route_centers.npy",
    "index_indptr": "index_indptr.npy",
    "index_words": "index_words.npy",
}


def _centroids_from(config: TrainConfig) -> tuple[np.ndarray, int]:
    """The centroids of the k-means bundle config.vocabulary_from (same features and K)."""
    from aefabmap_runtime.adapters.bundle_reader import load_bundle

    source = load_bundle(config.vocabulary_from)
    if source.quantizer_type != "kmeans":
        raise ConfigError(f"--vocabulary-from {config.vocabulary_from}: not a k-means bundle")
    if source.features != config.features or source.vocabulary_size != config.words:
        raise ConfigError(f"--vocabulary-from {config.vocabulary_from}: its features or word count differ from this training")
    return source.quantizer("flat-fp32").centroids, int(source.manifest["quantizer"].get("descriptors_clustered", 0))


def _train_index(sample: np.ndarray, per_image: list[np.ndarray], kind: FeatureKind, flat, config: TrainConfig):
    """Inverted index of the flat vocabulary: (quantiser, manifest entry, files, observations).

    The observations are the exact flat words of each training image, which the index
    reproduces on every training descriptor (its lists hold them).
    """
    from aefabmap_runtime.core.words.quantizer import IndexedCentroidQuantizer
    from aefabmap_trainer.centroid_index import build_lists, fit_routing

    binary = kind.distance == "hamming"
    centers = fit_routing(sample, config.index_buckets, binary=binary,
                          config=KMeansConfig(config.kmeans_iterations, seed=config.seed))
    observations: list[np.ndarray] = []

    def assigned():
        for raw in tqdm(per_image, desc="quantise + index", disable=not config.show_progress, mininterval=1.0):
            if not len(raw):
                observations.append(np.zeros(0, np.int64))
                continue
            vectors = kind.vectors(raw)
            words = flat.quantize(vectors)
            observations.append(np.unique(words))
            yield vectors, words

    indptr, words = build_lists(centers, flat.centroids, assigned())
    quantizer = IndexedCentroidQuantizer(flat.centroids, centers, indptr, words)
    manifest = {"files": dict(INDEX_FILE_NAMES), "buckets": int(centers.shape[0]), "entries": int(words.size),
                "distance": "hamming" if binary else "l2"}
    files = {INDEX_FILE_NAMES["index_centers"]: centers, INDEX_FILE_NAMES["index_indptr"]: indptr,
             INDEX_FILE_NAMES["index_words"]: words}
    return quantizer, manifest, files, observations
