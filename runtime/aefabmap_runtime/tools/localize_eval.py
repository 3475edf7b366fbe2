"""Evaluate localization against a map built once (`eval --localize`, docs/localization.md).

The map of a state directory is loaded read-only (adapters/node_state.py open_frozen_map); its
frame counter says where the frames that built it end, so the sequence's frames from there on
are the queries, each ranked and verified against the map and never inserted. Only the map's
frames can be right answers: the ground truth is cut to queries x map frames, and the metrics
are those of the full protocol (docs/evaluation.md) over that cut. The state directory is
never written.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.adapters.node_state import open_frozen_map
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.pr_metrics import evaluate_predictions
from aefabmap_runtime.tools.sequence_eval import SequenceRun, load_ground_truth, run_sequence

log = logging.getLogger("aefabmap.eval")


@dataclass
class LocalizationRun:
    """The queries' run (frames `first`..N-1 of the sequence) and the map they ran against."""

    run: SequenceRun
    first: int
    map_places: int


def localize_sequence(bundle_path, images_dir, gt_path, state, config: DetectorConfig | None = None,
                      tolerance: int = 10, show_progress: bool = True, workers: int = 1) -> tuple[dict, LocalizationRun]:
    """Metrics of the frames after the map's last one, localized against the map of `state`.

    The map's frames are frames 0..first-1 of `images_dir` (first: the map's next frame);
    ConfigError when the sequence has no frame after them. Returns (metrics, the run)."""
    images = list_images(images_dir)
    gt = load_ground_truth(gt_path, len(images))
    detector = load_detector(bundle_path, config)
    directory = open_frozen_map(state, detector, log)
    try:
        first = detector.next_sequence
        if first >= len(images):
            raise ConfigError(f"the map in {state} was built over {first} frames; {images_dir} has {len(images)}: "
                              "no frame is left to localize (give the whole sequence, the map's frames first, and "
                              "its whole ground truth: the frames after the map's are localized)")
        places = detector.n_places
        run = run_sequence(detector, images[first:], keep_matrix=False, show_progress=show_progress, workers=workers)
    finally:
        directory.close()
    return localization_metrics(run, gt, first, tolerance), LocalizationRun(run, first, places)


def localization_metrics(run: SequenceRun, gt: np.ndarray, first: int, tolerance: int) -> dict:
    """The protocol's metrics of the queries (frames first..N-1) over the cut ground truth
    (a query's true places are map frames only); "verified" as for a whole sequence."""
    n = gt.shape[0]
    cut = np.zeros_like(gt)
    cut[first:, :first] = gt[first:, :first]

    def padded(values: np.ndarray, fill) -> np.ndarray:
        out = np.full(n, fill, values.dtype)
        out[first:] = values
        return out

    metrics = evaluate_predictions(padded(run.best_frames, -1), padded(run.scores, 0.0), cut, tolerance)
    metrics["verified"] = evaluate_predictions(padded(run.verified_frames, -1), padded(run.verified_scores, 0.0),
                                               cut, tolerance)
    metrics.update({"queries": n - first, "map_frames": first, "peak_rss_mb": run.peak_rss_mb, "wall_s": run.wall_s})
    return metrics


def state_digest(directory: str | Path) -> str:
    """One sha256 over every file of a directory (relative paths and bytes, in name order): a
    state directory that nothing wrote keeps it."""
    import hashlib

    h = hashlib.sha256()
    root = Path(directory)
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes())
    return h.hexdigest()
