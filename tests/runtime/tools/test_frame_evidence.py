"""Per-frame evidence (JSON lines) and failure match images, on hand-made results and end to end."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from aefabmap.cli.main import main
from aefabmap_runtime.core.records.messages import Candidate, FrameResult
from aefabmap_runtime.tools.frame_evidence import (
    failure_cases,
    frame_records,
    match_image,
    write_failure_images,
)
from aefabmap_runtime.tools.reporting import format_table
from aefabmap_runtime.tools.synthetic_route import make_demo_sequence
from tests.conftest import REPO


def result(seq, n_keypoints=300, best=None, verified_frame=None, candidates=()) -> FrameResult:
    return FrameResult(
        sequence=seq, stamp_ns=seq, n_keypoints=n_keypoints, n_words=n_keypoints // 2,
        best_place=best, best_frame=best, score=0.5 if best is not None else 0.0, p_new=0.5,
        loop=verified_frame is not None, verified=verified_frame is not None,
        verified_place=verified_frame, verified_frame=verified_frame, candidates=list(candidates),
    )


def cand(frame, rank, checked=False, verified=False, inliers=0, points=None) -> Candidate:
    return Candidate(place=frame, frame=frame, rank=rank, probability=0.1, llr=2.0, checked=checked,
                     source="fabmap" if checked else None, verified=verified, inliers=inliers,
                     matches=inliers + 5, model="H" if checked else None, inlier_points=points)


@pytest.fixture
def hand_made():
    """6 frames; frames 4 and 5 revisit 0 and 1. Frame 3 is a false positive (verified to 2, no
    loop), frame 4 a miss whose true place 0 was checked and rejected, frame 5 a true positive,
    frame 2 a blank wall (3 keypoints), frame 1 saw an empty map."""
    gt = np.zeros((6, 6), bool)
    gt[4, 0] = gt[5, 1] = True
    pts = np.array([[10, 10, 12, 11], [50, 40, 52, 41], [80, 70, 81, 69]], np.float32)
    results = [
        result(0),
        result(1),
        result(2, n_keypoints=3, best=0, candidates=[cand(0, 0)]),
        result(3, best=2, verified_frame=2, candidates=[cand(2, 0, True, True, 40, pts), cand(0, 1)]),
        result(4, best=2, candidates=[cand(2, 0, True), cand(0, 1, True, inliers=9, points=pts[:2])]),
        result(5, best=1, verified_frame=1, candidates=[cand(1, 0, True, True, 60)]),
    ]
    return results, gt


def test_records_say_evidence_choice_and_correctness(hand_made):
    results, gt = hand_made
    recs = list(frame_records(results, gt, tolerance=0, min_keypoints=15))
    assert [r["evidence"] for r in recs] == ["unchecked", "unchecked", "none", "verified", "rejected", "verified"]
    assert [r["outcome"] for r in recs] == ["true_negative"] * 3 + ["false_positive", "miss", "true_positive"]
    assert recs[3]["chosen_frame"] == 2 and recs[3]["correct"]["verified_tolerant"] is False
    assert recs[4]["chosen_frame"] is None and recs[4]["correct"]["verified_strict"] is None
    assert recs[4]["correct"]["raw_strict"] is False and recs[4]["true_place_candidate"] is True
    assert recs[5]["correct"] == {"raw_strict": True, "raw_tolerant": True, "verified_strict": True, "verified_tolerant": True}
    checked = [c["frame"] for c in recs[4]["candidates"] if c["checked"]]
    assert checked == [2, 0] and recs[4]["candidates"][1]["inliers"] == 9
    assert "inlier_points" not in recs[3]["candidates"][0]
    json.dumps(recs)  # JSON-able as a whole
    no_gt = next(frame_records(results, None, 0, 15))
    assert "correct" not in no_gt and "outcome" not in no_gt


def test_failures_are_false_positives_and_misses_with_their_true_place(hand_made, tmp_path):
    results, gt = hand_made
    recs = list(frame_records(results, gt, tolerance=0, min_keypoints=15))
    cases = failure_cases(results, recs, tolerance=0)
    assert [(f, kind, c.frame) for f, kind, c in cases] == [(3, "false_positive", 2), (4, "miss", 0)]
    images = []
    for i in range(6):
        p = tmp_path / f"{i}.png"
        cv2.imwrite(str(p), np.full((120, 160), 40 * i, np.uint8))
        images.append(p)
    written = write_failure_images(tmp_path / "fail", images, cases)
    assert [p.name for p in written] == ["000003_false_positive_000002.png", "000004_miss_000000.png"]
    fp = cv2.imread(str(written[0]))
    assert fp.shape == (22 + 240, 640, 3)  # 160-px frames are shown twice as large
    red = (fp[..., 2] > 200) & (fp[..., 1] < 60) & (fp[..., 0] < 60)
    assert red.sum() > 50  # the inlier lines are drawn


def test_match_image_without_points_is_just_the_pair():
    img = match_image(np.zeros((250, 360), np.uint8), np.zeros((240, 370), np.uint8), None, "x", (0, 0, 255))
    assert img.shape == (250 + 22, 730, 3) and img[22:].max() == 0


def test_table_leads_with_given_order_and_labels_strict_and_tolerant():
    row = {"recall_at_100p_tolerant": 0.9, "auc_tolerant": 0.95, "max_f1_tolerant": 0.9, "recall_at_100p": 0.5,
           "auc": 0.6, "max_f1": 0.6, "false_positives": 0, "false_positives_strict": 7}
    lines = format_table({"fabmap verified (output)": row, "fabmap raw (llr)": {**row, "false_positives": None}}).splitlines()
    assert "R@100P tolerant" in lines[0] and "R@100P strict" in lines[0] and "FP tolerant" in lines[0]
    assert lines[2].startswith("| fabmap verified (output) | 90.0 |") and "| 0 | 7 |" in lines[2]
    assert "| - | 7 |" in lines[3]


def test_eval_writes_frames_and_failures_consistent_with_its_json(tmp_path):
    """End to end on the generated demo route with the shipped bundle (a few seconds)."""
    seq = tmp_path / "seq"
    make_demo_sequence(seq, n_frames=60, size=(320, 240))
    out = tmp_path / "eval.json"
    frames, fail = tmp_path / "frames.jsonl", tmp_path / "fail"
    code = main(["eval", "--model", str(REPO / "aefabmap" / "data" / "default_bundle"), "--images", str(seq),
                 "--gt", str(seq / "gt.npy"), "--exclude", "5", "--json", str(out), "--frames", str(frames),
                 "--failures", str(fail), "--no-progress"])
    assert code == 0
    doc = json.loads(out.read_text())
    recs = [json.loads(line) for line in frames.read_text().splitlines()]
    assert [r["frame"] for r in recs] == list(range(60))
    verified = doc["verified"]
    assert sum(r["outcome"] == "false_positive" for r in recs) == verified["false_positives"]
    assert sum(r["outcome"] == "true_positive" for r in recs) == verified["predictions"] - verified["false_positives"]
    assert sum(r["correct"]["raw_tolerant"] is False for r in recs) == doc["false_positives"]
    for r in recs:
        if r["verified"]:
            chosen = [c for c in r["candidates"] if c["verified"]]
            assert chosen and chosen[0]["frame"] == r["chosen_frame"] and chosen[0]["checked"]
            assert r["inliers"] == chosen[0]["inliers"]
    expected = {r["frame"] for r in recs if r["outcome"] == "false_positive" or (r["outcome"] == "miss" and r["true_place_candidate"])}
    assert {int(p.name[:6]) for p in fail.glob("*.png")} == expected


def test_failures_need_verification(tmp_path):
    code = main(["eval", "--model", str(REPO / "aefabmap" / "data" / "default_bundle"), "--images", str(tmp_path),
                 "--gt", str(tmp_path / "gt.npy"), "--no-verify", "--failures", str(tmp_path / "f")])
    assert code == 2 and not (tmp_path / "f").exists()


def test_revisit_split_says_where_each_missed_revisit_was_lost():
    from aefabmap_runtime.tools.frame_evidence import format_revisit_split, revisit_split

    def checked(frame, nfa):
        c = cand(frame, 0, checked=True, inliers=5)
        c.nfa = nfa
        return c

    results = [
        result(0), result(1), result(2), result(3),
        result(4, best=0, verified_frame=0, candidates=[cand(0, 0, checked=True, verified=True, inliers=40)]),
        result(5, best=3, candidates=[cand(3, 0)]),  # true place 1 is not a candidate
        result(6, best=2, candidates=[checked(2, None)]),  # checked, nothing fitted
        result(7, best=3, candidates=[checked(3, 1.5)]),  # no geometric evidence
        result(8, best=3, candidates=[checked(3, -2.0)]),  # some, below 0 but above the bar
        result(9, best=2, verified_frame=0, candidates=[cand(0, 0, checked=True, verified=True, inliers=30)]),
    ]
    gt = np.zeros((10, 10), bool)
    for q, p in ((4, 0), (5, 1), (6, 2), (7, 3), (8, 3), (9, 2)):
        gt[q, p] = gt[p, q] = True
    records = list(frame_records(results, gt, tolerance=0, min_keypoints=8))
    assert [r.get("miss_reason") for r in records[5:9]] == ["not_a_candidate", "no_model", "nfa_at_least_0",
                                                            "nfa_below_0"]
    split = revisit_split(records)
    assert (split["revisits"], split["verified"], split["wrong_place"], split["true_place_checked"]) == (6, 1, 1, 4)
    assert sum(split["misses"].values()) == 4
    assert "revisit frames 6: verified 1, wrong place 1" in format_revisit_split(split)
