"""Evaluate a model bundle on an image sequence with ground truth (protocol: docs/evaluation.md).

Adapter around LoopClosureDetector: reads image files in name order, runs every frame,
collects predictions, timings and the score matrix, and computes the metrics.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.frame_pipeline import pipelined
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.adapters.npy_file import load_npy
from aefabmap_runtime.core.detector import (
    DetectorConfig,
    FrameResult,
    LoopClosureDetector,
)
from aefabmap_runtime.tools.pr_metrics import evaluate_predictions


def load_ground_truth(path: str | Path, n_frames: int) -> np.ndarray:
    """Load a bool (N, N) ground-truth matrix (.npy, no pickles) and check it fits the sequence.

    The header is checked before loading (see npy_file.load_npy): a shape other than
    (n_frames, n_frames) is refused without reading the data.
    """
    try:
        with open(path, "rb") as fh:
            gt = load_npy(fh, f"ground truth {path}", kinds="biuf", shape=(n_frames, n_frames))
    except OSError as exc:
        raise InputError(f"cannot read ground truth {path}: {exc.strerror or exc}") from exc
    return gt.astype(bool)


@dataclass
class SequenceRun:
    """Per-frame results of one detector over a sequence, with timings and the score matrix."""

    results: list[FrameResult]
    stage_ms: dict[str, np.ndarray]
    score_matrix: np.ndarray | None = None  # (N, N) float32: score of frame j for query i
    peak_rss_mb: float = 0.0
    wall_s: float = 0.0
    extra: dict = field(default_factory=dict)
    images: list[Path] = field(default_factory=list)  # the frames, in order (evidence images)
    ground_truth: np.ndarray | None = None  # (N, N) bool, when the run was scored

    @property
    def best_frames(self) -> np.ndarray:
        return np.array([-1 if r.best_frame is None else r.best_frame for r in self.results], np.int64)

    @property
    def scores(self) -> np.ndarray:
        return np.array([r.score for r in self.results], np.float64)

    @property
    def verified_frames(self) -> np.ndarray:
        """(N,) matched frame of the verified output, -1 where no candidate was verified."""
        return np.array([-1 if not r.verified or r.verified_frame is None else r.verified_frame for r in self.results], np.int64)

    @property
    def verified_scores(self) -> np.ndarray:
        """(N,) score of the verified output: its significance -log10 NFA (0 where nothing was verified).

        Comparable across models (H and F inlier counts are not) and across frames with
        different numbers of matches; a result without an NFA falls back to its inlier count.
        """
        return np.array([(0.0 if not r.verified else -r.nfa if getattr(r, "nfa", None) is not None else r.inliers)
                         for r in self.results], np.float64)


def run_sequence(detector: LoopClosureDetector, images: list[Path], keep_matrix: bool = True, show_progress: bool = True,
                 workers: int = 1) -> SequenceRun:
    """Run every image through the detector; keep the full score rows when keep_matrix.
    workers: threads that work on frames (adapters/frame_pipeline.py; the same results)."""
    n = len(images)
    matrix = np.zeros((n, n), np.float32) if keep_matrix and n <= 20000 else None
    results = []
    stages: dict[str, list[float]] = {"decode": [], "features": [], "quantise": [], "inference": []}
    if detector.store is not None:
        stages["verification"] = []
    loop = FrameLoop(detector, strict=True)  # an unreadable frame stops the run: gt indices must hold
    t_start = time.perf_counter()
    frames = ((i, path, i) for i, path in enumerate(images))
    progress = tqdm(total=len(images), desc="frames", disable=not show_progress, mininterval=1.0)
    for i, out in pipelined(loop, frames, workers):
        progress.update()
        res = out.result
        stages["decode"].append(out.decode_ms)
        for k, v in res.timings_ms.items():
            stages.setdefault(k, []).append(v)
        if matrix is not None:
            row = detector.last_scores()
            if row is not None and row.size:
                frames = detector.place_frames()
                matrix[i, frames] = row
        results.append(res)
    progress.close()
    wall = time.perf_counter() - t_start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return SequenceRun(results, {k: np.asarray(v) for k, v in stages.items()}, matrix, peak, wall)


def summarise_timings(stage_ms: dict[str, np.ndarray]) -> dict:
    """Median and p95 per stage and of the total, in ms."""
    out = {}
    total = None
    for k, v in stage_ms.items():
        if v.size == 0:
            continue
        out[k] = {"median": float(np.median(v)), "p95": float(np.percentile(v, 95))}
        total = v if total is None else total + v
    if total is not None:
        out["total"] = {"median": float(np.median(total)), "p95": float(np.percentile(total, 95))}
    return out


def evaluate_run(run: SequenceRun, gt: np.ndarray, tolerance: int = 10) -> dict:
    """Metrics (strict and tolerant), timings and memory of a run, as a JSON-able dict.

    When the detector verified its candidates, metrics["verified"] holds the same metric keys
    for the verified output: prediction = the verified frame, score = its inlier count,
    unverified frames make no prediction.
    """
    metrics = evaluate_predictions(run.best_frames, run.scores, gt, tolerance)
    metrics["ms_per_frame"] = summarise_timings(run.stage_ms)
    metrics["peak_rss_mb"] = run.peak_rss_mb
    metrics["wall_s"] = run.wall_s
    if "verification" in run.stage_ms:
        verified = evaluate_predictions(run.verified_frames, run.verified_scores, gt, tolerance)
        verified["ms_per_frame"] = metrics["ms_per_frame"]
        verified["verification_ms"] = metrics["ms_per_frame"].get("verification", {})
        tried = np.array([r.candidates_tried for r in run.results], np.float64)
        verified["mean_candidates_tried"] = float(tried.mean()) if tried.size else 0.0
        verified["geometry_models"] = {
            m: int(sum(1 for r in run.results if r.verified and r.geometry_model == m)) for m in ("F", "E", "H")
        }
        verified.update(run.extra.get("verified", {}))
        metrics["verified"] = verified
    return metrics


def public(metrics: dict) -> dict:
    """Drop in-memory-only entries (PR curves) from a metrics dict, also in nested dicts."""
    return {k: public(v) if isinstance(v, dict) else v for k, v in metrics.items() if not k.startswith("_")}


def evaluate_bundle(bundle_path, images_dir, gt_path, config: DetectorConfig | None = None, tolerance: int = 10,
                    show_progress: bool = True, after_run=None, workers: int = 1) -> tuple[dict, SequenceRun]:
    """Run a bundle over an image directory and score it against gt_path.

    after_run: called with the detector once every frame went through (e.g. to save its map).
    workers: threads that work on frames (run_sequence).
    """
    images = list_images(images_dir)
    gt = load_ground_truth(gt_path, len(images))
    detector = load_detector(bundle_path, config)
    run = run_sequence(detector, images, show_progress=show_progress, workers=workers)
    if after_run is not None:
        after_run(detector)
    if detector.store is not None:
        store = detector.store
        run.extra["verified"] = {
            "config": dataclasses.asdict(detector.config.verification),
            "temporal_frames": detector.config.temporal_frames,
            "temporal_tolerance": detector.config.temporal_tolerance,
            "store_places": len(store),
            "store_bytes": store.nbytes(),
            "store_bytes_per_place": store.nbytes() / max(len(store), 1),
            "store_bytes_per_keypoint": store.bytes_per_keypoint,
        }
    run.images, run.ground_truth = images, gt
    metrics = evaluate_run(run, gt, tolerance)
    metrics.update(
        {
            "model": str(bundle_path),
            "images": str(images_dir),
            "scorer": detector.config.scorer,
            "fabmap_score": detector.config.fabmap_score,
            "exclude": detector.config.exclude,
            "quantizer": detector.bundle.quantizer_type,
            "quantizer_variant": detector.config.quantizer_variant,
            "features": detector.bundle.features.to_dict(),
            "vocabulary_size": detector.bundle.vocabulary_size,
            "training": detector.bundle.manifest.get("training", {}),
            "mean_keypoints": float(np.mean([r.n_keypoints for r in run.results])),
            "mean_words": float(np.mean([r.n_words for r in run.results])),
            "map_bytes": detector.map_bytes(),
        }
    )
    return metrics, run
