"""`aefabmap bench quantizer`: milliseconds to quantise 500 real descriptors on one thread.

Times what the detector's "quantise" stage does per frame: raw descriptors in, word ids out
(`quantize_raw`: packed ORB bits go straight to a vocabulary tree with bit centres; the flat
vocabulary and the autoencoder get the unpacked float vectors, the unpacking included). The
descriptors come from the images of <data>/train/scene15 (sorted, first ones until 500),
extracted with the bundle's own feature settings; without that folder, from synthetic frames
the project generates (`synthetic_route`). Runs in a spawned process pinned to one CPU with
one BLAS/OpenMP/onnxruntime thread.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import BundleError, ConfigError
from aefabmap_runtime.core.profiles import bundle_variants
from aefabmap_runtime.tools.node_process import SINGLE_THREAD_ENV
from aefabmap_runtime.tools.stream_bench import _stats, machine_info, pin_one_cpu, run_spawned_single_thread

#: Quantiser variants: the bundle's quantizer type and, for the autoencoder, the precision.
VARIANTS = ("kmeans-flat", "kmeans-flat-fp32", "kmeans-indexed", "kmeans-tree", "ae-fp32", "ae-int8")
SAMPLE_SUBDIR = Path("train") / "scene15"


@dataclass(frozen=True)
class QuantizerBenchConfig:
    """bundle: model bundle directory. variant: None (the bundle's own: "kmeans-indexed" when a
    k-means bundle has an index, "ae-fp32" for AE bundles), one of VARIANTS, or "fp32"/"int8". descriptors: per timed call. repeats: timed calls (after
    `warmup`). data: data root holding train/scene15 (None: synthetic frames)."""

    bundle: str
    variant: str | None = None
    descriptors: int = 500
    repeats: int = 200
    warmup: int = 5
    data: str | None = None
    single_core: bool = True

    def __post_init__(self) -> None:
        if self.descriptors < 1 or self.repeats < 1 or self.warmup < 0:
            raise ConfigError("descriptors and repeats must be >= 1, warmup >= 0")
        if self.variant is not None and self.variant not in VARIANTS + ("fp32", "int8"):
            raise ConfigError(f"variant must be one of {VARIANTS + ('fp32', 'int8')}, got {self.variant!r}")


def resolve_variant(manifest_quantizer: dict, variant: str | None) -> str:
    """The VARIANTS name of `variant` for a bundle whose manifest quantizer entry is given
    (None: the bundle's default; a k-means bundle with an index runs "kmeans-indexed" or "kmeans-flat")."""
    have = bundle_variants(manifest_quantizer)
    if have[0].startswith("ae-"):
        variant = {"fp32": "ae-fp32", "int8": "ae-int8"}.get(variant, variant)
    if variant is None:
        return have[0]
    if variant not in have:
        raise ConfigError(f"this {manifest_quantizer.get('type')} bundle has the variants {have}, not {variant!r}")
    return variant


#: Bundle.quantizer() variant argument of each VARIANTS name.
LOADER_VARIANT = {"kmeans-flat": "flat", "kmeans-flat-fp32": "flat-fp32", "kmeans-indexed": "fp32", "kmeans-tree": "fp32", "ae-fp32": "fp32",
                  "ae-int8": "int8"}


def sample_descriptors(features, n: int, data: str | None) -> tuple[np.ndarray, str]:
    """Up to n raw descriptors (the kind's raw form) and where they came from."""
    from aefabmap_runtime.adapters.frames import load_image
    from aefabmap_runtime.adapters.image_folder import IMAGE_SUFFIXES
    from aefabmap_runtime.core.features.features import FeatureExtractor

    extractor = FeatureExtractor(features)
    folder = Path(data) / SAMPLE_SUBDIR if data else None
    if folder is not None and folder.is_dir():
        images = (load_image(p) for p in sorted(folder.rglob("*")) if p.suffix.lower() in IMAGE_SUFFIXES)
        source = str(folder)
    else:
        from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

        frames, _ = generate_loop_sequence(40, seed=0, size=(640, 480))
        images = iter(frames)
        source = "synthetic frames (synthetic_route, seed 0)"
    got, count = [], 0
    for image in images:
        d = extractor.extract(image).descriptors
        got.append(d)
        count += len(d)
        if count >= n:
            break
    raw = np.concatenate(got)[:n] if got else features.spec.empty()
    if raw.shape[0] == 0:
        raise ConfigError(f"no descriptors found in {source}")
    return np.ascontiguousarray(raw), source


def bench_quantizer(config: QuantizerBenchConfig) -> dict:
    """Median and p95 ms of one quantize call on `descriptors` raw descriptors (module doc)."""
    if not Path(config.bundle).is_dir():
        raise BundleError(f"model bundle {config.bundle} does not exist")
    if not config.single_core:
        return _bench_here(config)
    return run_spawned_single_thread(_bench_here, config)


def _bench_here(config: QuantizerBenchConfig) -> dict:
    import cv2

    from aefabmap_runtime.adapters.bundle_reader import load_bundle
    from aefabmap_runtime.adapters.state_dir import bundle_id
    from aefabmap_runtime.core.words.quantizer import quantize_raw

    pinned = None
    if config.single_core:
        cv2.setNumThreads(1)
        pinned = pin_one_cpu()
    bundle = load_bundle(config.bundle)
    variant = resolve_variant(bundle.manifest["quantizer"], config.variant)
    quantizer = bundle.quantizer(LOADER_VARIANT[variant], threads=1)
    kind = bundle.features.spec
    raw, source = sample_descriptors(bundle.features, config.descriptors, config.data)
    for _ in range(config.warmup):
        quantize_raw(quantizer, kind, raw)
    times, cpu = [], []
    for _ in range(config.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        quantize_raw(quantizer, kind, raw)
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    stats, cpu_stats = _stats(times), _stats(cpu)
    n = raw.shape[0]
    q = bundle.manifest["quantizer"]
    doc = {
        "benchmark": "quantizer",
        "bundle": str(config.bundle),
        "bundle_id": bundle_id(bundle.manifest),
        "variant": variant,
        "feature_kind": bundle.features.kind,
        "words": bundle.vocabulary_size,
        "descriptors": n,
        "descriptor_source": source,
        # Per 500 descriptors: scaled when fewer were found (linear in N for every variant).
        "ms_per_500_median": round(stats["median"] * 500 / n, 3),
        "ms_per_500_p95": round(stats["p95"] * 500 / n, 3),
        # CPU time of the process (one pinned thread): what the call costs when the machine is
        # shared, without the time it waited for the CPU.
        "cpu_ms_per_500_median": round(cpu_stats["median"] * 500 / n, 3),
        "cpu_ms_per_500_p95": round(cpu_stats["p95"] * 500 / n, 3),
        "ms_per_call": stats,
        "repeats": config.repeats,
        "timed": "raw descriptors -> word ids (quantize_raw), as the detector's quantise stage",
        "single_core": config.single_core,
        "pinned_cpu": pinned,
        "threads_env": {k: os.environ.get(k) for k in SINGLE_THREAD_ENV},
        "machine": machine_info(),
    }
    if q.get("type") == "kmeans-tree":
        doc["tree"] = {k: q.get(k) for k in ("branching", "nodes", "depth", "distance")}
    if variant == "kmeans-indexed":
        doc["index"] = {k: q["index"].get(k) for k in ("buckets", "entries", "distance")}
    return doc
