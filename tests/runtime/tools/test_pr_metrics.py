"""Metrics of docs/evaluation.md on hand-made predictions."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap import InputError
from aefabmap_runtime.tools.pr_metrics import evaluate_predictions


def make_gt(n=40):
    gt = np.zeros((n, n), bool)
    for i in range(30, 40):  # frames 30..39 revisit 10..19 (5-frame bands)
        gt[i, i - 20 : i - 15] = True
    return gt


def test_perfect_predictions():
    gt = make_gt()
    best = np.full(40, -1)
    scores = np.zeros(40)
    best[30:40] = np.arange(10, 20)
    scores[30:40] = 0.9
    m = evaluate_predictions(best, scores, gt)
    assert m["relevant_frames"] == 10
    assert m["recall_at_100p"] == 1.0 and m["recall_at_100p_tolerant"] == 1.0
    assert m["auc"] == pytest.approx(1.0) and m["max_f1"] == pytest.approx(1.0)


def test_tolerance_and_ranking():
    gt = make_gt()
    best = np.full(40, -1)
    scores = np.zeros(40)
    # Frame 30 matches 10 (exact), frame 31 matches 25 (off the band by 9: tolerant only),
    # frame 32 matches 0 (wrong, off by 12), frame 5 predicts a loop that does not exist.
    best[[30, 31, 32, 5]] = [10, 25, 0, 1]
    scores[[30, 31, 32, 5]] = [0.99, 0.98, 0.97, 0.5]
    m = evaluate_predictions(best, scores, gt, tolerance=10)
    assert m["recall_at_100p"] == pytest.approx(0.1)  # only the first before a strict FP
    assert m["threshold_at_100p"] == pytest.approx(0.99)
    assert m["recall_at_100p_tolerant"] == pytest.approx(0.2)
    assert m["threshold_at_100p_tolerant"] == pytest.approx(0.98)
    # Tolerant: precision 1 at recall .1, .2; then 2/3 at .2, 2/4 at .2 -> AUC = 0.2.
    assert m["auc_tolerant"] == pytest.approx(0.2)
    assert m["auc"] == pytest.approx(0.1)


def test_ties_count_as_one_threshold():
    gt = make_gt()
    best = np.full(40, -1)
    scores = np.zeros(40)
    best[[30, 31]] = [10, 0]  # right, wrong
    scores[[30, 31]] = 0.99  # tied: cannot separate them
    m = evaluate_predictions(best, scores, gt, tolerance=0)
    assert m["recall_at_100p"] == 0.0
    assert m["threshold_at_100p"] is None


def test_shape_mismatch_is_an_error():
    with pytest.raises(InputError, match="ground truth"):
        evaluate_predictions(np.zeros(5, int), np.zeros(5), np.zeros((4, 4), bool))


def test_false_positives_count_wrong_predictions_whatever_their_score():
    gt = make_gt()
    best = np.full(40, -1)
    best[30:40] = np.arange(10, 20)  # frame i predicts i - 20: inside its band i-20..i-16
    best[5] = 0  # frame 5 has no loop at all
    best[36] = 2  # band 16..20: 14 frames off, beyond the tolerance
    scores = np.linspace(0.0, 1.0, 40)
    m = evaluate_predictions(best, scores, gt, tolerance=10)
    assert (m["false_positives"], m["false_positives_strict"]) == (2, 2)
    best[31] = 8  # band 11..15: 3 frames off, right only with the tolerance
    m = evaluate_predictions(best, scores, gt, tolerance=10)
    assert (m["false_positives"], m["false_positives_strict"]) == (2, 3)
