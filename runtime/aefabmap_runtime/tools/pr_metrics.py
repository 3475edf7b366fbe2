"""Loop-closure metrics of the evaluation protocol, docs/evaluation.md (pure numpy).

Each query frame i has at most one prediction: its best candidate j* (or none) and a score.
A threshold t sweeps every distinct score; frame i is a predicted positive when s_i >= t.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import InputError

TOLERANCE_FRAMES = 10


@dataclass
class PRCurve:
    """Precision and recall at each distinct threshold, thresholds descending."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray

    def recall_at_full_precision(self) -> tuple[float, float | None]:
        """Largest recall at a threshold where precision is exactly 1, and that threshold."""
        ok = self.precision >= 1.0
        if not np.any(ok):
            return 0.0, None
        k = int(np.flatnonzero(ok)[np.argmax(self.recall[ok])])
        return float(self.recall[k]), float(self.thresholds[k])

    def auc(self) -> float:
        """Step-wise area under the PR curve, recall on x."""
        r = np.concatenate([[0.0], self.recall])
        return float(np.sum(np.diff(r) * self.precision))

    def max_f1(self) -> tuple[float, float | None]:
        denom = self.precision + self.recall
        f1 = np.where(denom > 0, 2 * self.precision * self.recall / np.where(denom > 0, denom, 1), 0.0)
        if f1.size == 0:
            return 0.0, None
        k = int(np.argmax(f1))
        return float(f1[k]), float(self.thresholds[k])


def correct_predictions(best_frame: np.ndarray, gt: np.ndarray, tolerance: int) -> np.ndarray:
    """(N,) bool: prediction j* of frame i is right, i.e. gt[i, k] for some |k - j*| <= tolerance.

    best_frame: (N,) int, -1 where a frame made no prediction.
    """
    n = gt.shape[0]
    ok = np.zeros(n, bool)
    for i in np.flatnonzero(best_frame >= 0):
        j = int(best_frame[i])
        lo, hi = max(0, j - tolerance), min(n, j + tolerance + 1)
        ok[i] = bool(gt[i, lo:hi].any())
    return ok


def pr_curve(scores: np.ndarray, has_prediction: np.ndarray, correct: np.ndarray, n_relevant: int) -> PRCurve:
    """PR curve over distinct thresholds of the scores of frames that made a prediction."""
    s = scores[has_prediction]
    c = correct[has_prediction]
    if s.size == 0:
        return PRCurve(np.zeros(0), np.zeros(0), np.zeros(0))
    order = np.argsort(-s, kind="stable")
    s, c = s[order], c[order]
    tp = np.cumsum(c)
    fp = np.cumsum(~c)
    # Only the last index of each run of equal scores is a reachable threshold.
    last = np.flatnonzero(np.r_[s[1:] != s[:-1], True])
    tp, fp = tp[last], fp[last]
    precision = tp / (tp + fp)
    recall = tp / max(n_relevant, 1)
    return PRCurve(s[last], precision, recall)


def evaluate_predictions(best_frame, scores, gt, tolerance: int = TOLERANCE_FRAMES) -> dict:
    """Strict and tolerant metrics for one method's predictions.

    best_frame: (N,) int best candidate frame per query (-1: no loop); scores: (N,) float;
    gt: (N, N) bool ground truth (gt[i, j]: frame i revisits frame j, j < i).
    false_positives: predicted loops (every frame with best_frame >= 0, whatever its score)
    whose frame is not a true match within the tolerance; false_positives_strict: not an exact
    true match. For a verified output (only verified frames predict) that is the count of
    wrong loop closures the product would have published.
    """
    best_frame = np.asarray(best_frame, np.int64)
    scores = np.asarray(scores, np.float64)
    gt = np.asarray(gt, bool)
    n = best_frame.size
    if gt.shape != (n, n):
        raise InputError(f"ground truth has shape {gt.shape}, expected ({n}, {n}) for {n} frames")
    if scores.shape != (n,):
        raise InputError(f"scores have shape {scores.shape}, expected ({n},)")
    gt = np.tril(gt, k=-1)
    n_relevant = int(gt.any(axis=1).sum())
    has = best_frame >= 0
    out = {"frames": int(n), "relevant_frames": n_relevant, "predictions": int(has.sum())}
    for suffix, tol, fp_key in (("", 0, "false_positives_strict"), ("_tolerant", tolerance, "false_positives")):
        correct = correct_predictions(best_frame, gt, tol)
        curve = pr_curve(scores, has, correct, n_relevant)
        r100, t100 = curve.recall_at_full_precision()
        f1, tf1 = curve.max_f1()
        out[f"recall_at_100p{suffix}"] = r100
        out[f"threshold_at_100p{suffix}"] = t100
        out[f"auc{suffix}"] = curve.auc()
        out[f"max_f1{suffix}"] = f1
        out[f"threshold_at_max_f1{suffix}"] = tf1
        out[f"_curve{suffix}"] = curve
        out[fp_key] = int((has & ~correct).sum())
    out["tolerance_frames"] = tolerance
    return out
