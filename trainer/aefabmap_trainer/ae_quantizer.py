"""Trainer entry for the AE-VQ quantiser (`aefabmap train --quantizer ae`).

train autoencoder -> k-means on latent codes -> ONE fp32 ONNX graph -> static QDQ int8 copy,
and a JSON-able manifest entry describing both files. With the "assign" objective
(trainer/aefabmap_trainer/assign_objective.py) the encoder and its K words are trained together and the trained
codebook is exported as it is (no k-means afterwards).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError

if TYPE_CHECKING:  # torch stays a lazy import: the runtime never loads this module
    from aefabmap_trainer.assign_objective import AssignConfig
    from aefabmap_trainer.autoencoder import AeConfig
    from aefabmap_trainer.match_pairs import MatchPairs
    from aefabmap_trainer.multiview import Tracks

FP32_NAME = "quantizer_fp32.onnx"
INT8_NAME = "quantizer_int8.onnx"
# Held-out vectors on which the int8 graph is compared with the fp32 graph.
AGREEMENT_SAMPLE = 20_000
# Share of matching-pair groups (source images / frame pairs) held out for early stopping and
# for the pair word agreement reported in the manifest.
PAIR_VAL_FRACTION = 0.15
# Training objectives: reconstruction (+ matching term) then k-means on codes; or word assignment.
OBJECTIVES = ("recon", "assign")


def build_ae_quantizer(
    vectors: np.ndarray,
    *,
    words: int,
    seed: int,
    feature_kind: str,
    out_dir: Path,
    calibration_vectors: np.ndarray | None = None,
    config: AeConfig | None = None,
    kmeans_iterations: int = 25,
    progress=None,
    pairs: MatchPairs | None = None,
    objective: str = "recon",
    tracks: Tracks | None = None,
    assign: AssignConfig | None = None,
) -> dict:
    """Train the AE-VQ quantiser on training descriptor vectors and write its ONNX files.

    vectors: (N, D) float32 training descriptor vectors (ORB bits D=256 or SIFT D=128).
    words: vocabulary size K. seed: fixes subsampling, weights, k-means and calibration.
    out_dir: receives quantizer_fp32.onnx and quantizer_int8.onnx.
    calibration_vectors: (M, D) float32 for int8 calibration; default: `vectors`.
    config: AeConfig (None -> defaults). progress: optional callable(stage: str) for the CLI.
    pairs: matching descriptor pairs (trainer/aefabmap_trainer/match_pairs.py); split by group into training
        pairs (matching term, when config.match_weight > 0) and held-out pairs (early stopping,
        and "pair_word_agreement": the share of held-out pairs whose two descriptors get one word).
    objective: "recon" (config's reconstruction [+ matching] loss, then k-means on the codes) or
        "assign" (encoder and codebook trained on `tracks`, trainer/aefabmap_trainer/multiview.py, split by source
        image into training and held-out tracks; `assign`: AssignConfig, None -> defaults).
    Returns the manifest entry: {"type": "ae", "files": {...}, "latent_dim", "train", "int8_agreement", ...},
    plus "timings" (seconds per stage), which the caller takes out before it writes the manifest.
    Same inputs and seed -> byte-identical files.
    """
    from aefabmap_export.onnx_export import export_quantizer_onnx
    from aefabmap_export.quantize_int8 import quantize_int8
    from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer
    from aefabmap_trainer.autoencoder import AeConfig, train_autoencoder
    from aefabmap_trainer.latent_vocabulary import fit_latent_vocabulary

    config = config or AeConfig()
    if not isinstance(config, AeConfig):
        raise ConfigError(f"config must be an AeConfig, got {type(config).__name__}")
    if not isinstance(words, int) or words < 2:
        raise ConfigError(f"words must be an integer >= 2, got {words!r}")
    vectors = np.ascontiguousarray(vectors, dtype=np.float32)
    if vectors.ndim != 2 or vectors.shape[0] < words:
        raise InputError(f"need a (N, D) array with N >= words={words}, got shape {vectors.shape}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    def stage(name: str) -> None:
        if progress is not None:
            progress(name)

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    stage("autoencoder")
    train_pairs = val_pairs = None
    if pairs is not None and len(pairs):
        train_pairs, val_pairs = pairs.split(PAIR_VAL_FRACTION, seed)
    if objective not in OBJECTIVES:
        raise ConfigError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    if objective == "assign":
        from aefabmap_trainer.assign_objective import train_assign

        if tracks is None or len(tracks) < 4:
            raise InputError("the assign objective needs multi-view tracks")
        train_tracks, val_tracks = tracks.split(PAIR_VAL_FRACTION, seed)
        result = train_assign(vectors, train_tracks, val_tracks, words=words, feature_kind=feature_kind, seed=seed,
                              config=config, assign=assign)
        codebook = result.codebook
        vocab_entry = {"codebook": "trained", "objective": "assign", "seed": seed}
        timings["train_s"] = time.perf_counter() - t0
        encoder = result.model.encoder
    else:
        result = train_autoencoder(
            vectors, feature_kind=feature_kind, seed=seed, config=config,
            pairs=None if train_pairs is None else (train_pairs.a, train_pairs.b),
            val_pairs=None if val_pairs is None else (val_pairs.a, val_pairs.b),
            pair_groups=None if train_pairs is None else train_pairs.group,
        )
        timings["train_s"] = time.perf_counter() - t0
        encoder = result.model.encoder

        t0 = time.perf_counter()
        stage("latent k-means")
        vocab = fit_latent_vocabulary(
            encoder, vectors, words, seed=seed, max_iterations=kmeans_iterations, threads=result.config.threads
        )
        codebook = vocab.codebook
        vocab_entry = {"iterations": kmeans_iterations, "n_clustered": vocab.n_clustered, "seed": seed}
        timings["kmeans_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stage("onnx export")
    fp32_path = export_quantizer_onnx(encoder, codebook, out_dir / FP32_NAME)
    calib = vectors if calibration_vectors is None else calibration_vectors
    int8_path = quantize_int8(fp32_path, out_dir / INT8_NAME, calib, seed=seed)
    timings["export_s"] = time.perf_counter() - t0

    # Agreement of int8 with fp32 words on a sample of the training vectors (drawn with
    # seed + 7; calibration draws with `seed`, so the two overlap when N is small). An
    # optimistic figure: k-means fitted the codebook to these very vectors, so they sit
    # nearer to word centres than unseen descriptors do (both figures: CHANGELOG.md, "AE-FABMAP vs
    # FABMAP2 (issue 3)").
    d = vectors.shape[1]
    rng = np.random.default_rng(seed + 7)
    sample = vectors if vectors.shape[0] <= AGREEMENT_SAMPLE else vectors[
        np.sort(rng.choice(vectors.shape[0], AGREEMENT_SAMPLE, replace=False))
    ]
    q32 = OnnxQuantizer(fp32_path, vocabulary_size=words, descriptor_length=d, threads=result.config.threads)
    q8 = OnnxQuantizer(int8_path, vocabulary_size=words, descriptor_length=d, threads=result.config.threads)
    w32 = q32.quantize(sample)
    agreement = float(np.mean(w32 == q8.quantize(sample)))
    used = np.bincount(w32, minlength=words)
    pair_agreement = None
    if val_pairs is not None and len(val_pairs):
        pair_agreement = {
            variant: round(float(np.mean(q.quantize(val_pairs.a) == q.quantize(val_pairs.b))), 6)
            for variant, q in (("fp32", q32), ("int8", q8))
        } | {"pairs": len(val_pairs)}

    return {
        "type": "ae",
        "files": {"fp32": FP32_NAME, "int8": INT8_NAME},
        "latent_dim": int(encoder.latent_dim),
        "descriptor_length": int(d),
        "vocabulary_size": int(words),
        "train": result.summary(),
        ("kmeans" if objective == "recon" else "vocabulary"): vocab_entry,
        "int8_agreement": round(agreement, 6),
        "agreement_sample": int(sample.shape[0]),
        "words_used_fraction": round(float(np.mean(used > 0)), 6),
        "pair_word_agreement": pair_agreement,
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }


def descriptor_sample(image_paths, feature_kind: str, *, max_features: int = 500, limit: int | None = None) -> np.ndarray:
    """Descriptor vectors (N, D) float32 of the images at `image_paths`, concatenated in order.

    A small helper for tests and benchmarks; `limit` truncates the result to its first rows.
    """
    from aefabmap_runtime.adapters.frames import load_image
    from aefabmap_runtime.core.features.features import (
        FeatureConfig,
        FeatureExtractor,
        descriptor_vectors,
    )

    fx = FeatureExtractor(FeatureConfig(kind=feature_kind, max_features=max_features))
    d = fx.config.descriptor_length
    parts = []
    total = 0
    for p in image_paths:
        v = descriptor_vectors(fx.extract(load_image(p)).descriptors, feature_kind)
        parts.append(v)
        total += v.shape[0]
        if limit is not None and total >= limit:
            break
    out = np.concatenate(parts) if parts else np.zeros((0, d), np.float32)
    return out if limit is None else out[:limit]
