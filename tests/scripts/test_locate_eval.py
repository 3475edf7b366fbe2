"""scripts/locate_eval.py: every frame after the map located alone, scored by the ground truth."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence, write_sequence

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import locate_eval as le  # noqa: E402


def _sequence(root: Path, n: int = 40) -> tuple[Path, np.ndarray]:
    images, gt = generate_loop_sequence(n, seed=3, size=(640, 480))
    write_sequence(root, images, gt)
    return root, gt


def test_every_frame_after_the_map_gets_one_answer(tmp_path, capsys):
    from aefabmap.cli.demo import default_bundle

    folder, gt = _sequence(tmp_path / "seq")
    out = tmp_path / "locate.json"
    assert le.main(["--model", str(default_bundle()), "--images", str(folder), "--gt", str(folder / "gt.npy"),
                    "--exclude", "2", "--tolerance", "1", "--stream", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    split = le.first_revisit(gt)
    assert doc["split"] == split and 0 < split < len(gt) and doc["map_places"] == split - 2  # 2 held back
    assert [r["query"] for r in doc["answers"]] == list(range(split, len(gt)))
    sums = doc["sums"]
    assert sums["queries"] == len(gt) - split == sums["right"] + sums["wrong"] + sums["none"]
    assert sums["with_a_true_frame"] == int(gt[split:, :split].any(axis=1).sum())
    for r in doc["answers"]:  # a true frame among the map's places: not one of the two held back
        truth = np.flatnonzero(gt[r["query"], :split])
        assert r["has_truth"] == bool(truth.size) and r["truth_in_map"] == bool((truth < split - 2).any())
        assert (r["frame"] is None) == (r["answer"] == "none") and (r["frame"] is None or r["frame"] < split - 2)
    assert sums["right"] > 0 and sums["wrong_true_frame_a_place"] <= sums["wrong"]
    # streamed as a localizing node: every later frame once, answered with frames of the map's run
    # (its two held-back frames too, once their delay has passed)
    stream = doc["streamed"]
    assert [a["query"] for a in stream["answers"]] == list(range(split, len(gt)))
    assert stream["right"] + stream["wrong"] + stream["none"] == sums["queries"] and stream["right"] > 0
    assert all((a["frame"] is None) == (a["answer"] == "none") for a in stream["answers"])
    assert all(a["frame"] < split for a in stream["answers"] if a["frame"] is not None)
    printed = capsys.readouterr().out
    assert " right, " in printed and "streamed: " in printed


def test_a_ground_truth_without_revisits_needs_a_split(tmp_path):
    with pytest.raises(SystemExit, match="no revisit"):
        le.first_revisit(np.zeros((5, 5), bool))
    gt = np.zeros((5, 5), bool)
    gt[3, 1] = gt[1, 3] = True
    assert le.first_revisit(gt) == 3
