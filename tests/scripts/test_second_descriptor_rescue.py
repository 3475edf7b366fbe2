"""scripts/second_descriptor_rescue.py: weak pairs of an ORB run verified again with a second
bundle's descriptors, under a gate on the first descriptor's support, scored by the ground truth."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from aefabmap.cli.main import main as aefabmap_main
from aefabmap_runtime.core.features.features import FeatureConfig
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence, write_sequence
from tests.conftest import make_learned_bundle

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import second_descriptor_rescue as sdr  # noqa: E402


def test_a_rescue_needs_the_gate_and_the_bar_with_two_descriptors_counted():
    bar = -4.0
    tried = [{"frame": 9, "tries": [{"stored": 2, "first": -1.5, "second": -4.2, "inliers": 9},   # -4.2 + 0.3 > bar
                                    {"stored": 3, "first": -0.5, "second": -6.0, "inliers": 12}]},
             {"frame": 10, "tries": [{"stored": 4, "first": 0.7, "second": -8.0, "inliers": 15}]}]
    assert {f: t["stored"] for f, t in sdr.rescued(tried, 0.0, bar).items()} == {9: 3}
    assert sdr.rescued(tried, -1.0, bar) == {}  # frame 9's only passing pair has first -0.5
    assert {f: t["stored"] for f, t in sdr.rescued(tried, math.inf, bar).items()} == {9: 3, 10: 4}


def test_the_table_scores_first_loops_and_rescues_by_the_ground_truth():
    gt = np.zeros((12, 12), bool)
    gt[9, 3] = gt[10, 5] = gt[11, 1] = True
    records = [{"frame": i, "verified": False, "candidates": []} for i in range(12)]
    records[11].update(verified=True, chosen_frame=1)
    tried = [{"frame": 9, "tries": [{"stored": 3, "first": -0.5, "second": -6.0, "inliers": 12}]},
             {"frame": 10, "tries": [{"stored": 0, "first": 0.7, "second": -8.0, "inliers": 15}]}]
    gated, open_ = sdr.score(records, tried, [0.0, math.inf], gt, 0, -4.0)
    assert gated == {"gate": 0.0, "first_right": 1, "first_wrong": 0, "rescued_right": 1, "rescued_wrong": 0,
                     "wrong": [], "pairs_tried": 1}
    assert open_["gate"] is None and open_["rescued_right"] == 1 and open_["wrong"] == [(10, 0, 0.7, -8.0)]


def test_a_real_run_retries_only_weak_candidates_of_unpublished_frames(tmp_path, capsys):
    from aefabmap.cli.demo import default_bundle

    images, gt = generate_loop_sequence(40, seed=3, size=(640, 480))
    folder = tmp_path / "seq"
    write_sequence(folder, images, gt)
    frames = tmp_path / "orb.jsonl"
    assert aefabmap_main(["eval", "--model", str(default_bundle()), "--images", str(folder), "--gt",
                          str(folder / "gt.npy"), "--exclude", "2", "--tolerance", "1", "--no-progress",
                          "--frames", str(frames)]) == 0
    out = tmp_path / "rescue.json"
    second, _ = make_learned_bundle(tmp_path / "learned",
                                    FeatureConfig(long_side=512, contrast_stretch=True, descriptor="learned"))
    assert sdr.main(["--second", str(second), "--images", str(folder), "--gt", str(folder / "gt.npy"),
                     "--frames", str(frames), "--tolerance", "1", "--gates", "0", "inf", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    records = [json.loads(line) for line in frames.read_text().splitlines()]
    published = {r["frame"] for r in records if r["verified"]}
    weak = {(r["frame"], c["frame"]) for r in records if not r["verified"] for c in r["candidates"]
            if c["checked"] and c["nfa"] is not None and -4.0 <= c["nfa"]}
    assert {(row["frame"], t["stored"]) for row in doc["tried"] for t in row["tries"]} == weak
    assert not published & {row["frame"] for row in doc["tried"]}
    gated, open_ = doc["table"]
    assert gated["first_right"] + gated["first_wrong"] == len(published) > 0
    assert gated["pairs_tried"] <= open_["pairs_tried"] == len(weak) > 0
    assert gated["rescued_right"] + gated["rescued_wrong"] <= open_["rescued_right"] + open_["rescued_wrong"]
    assert "gate     0: first " in capsys.readouterr().out


def test_records_of_another_sequence_are_refused(tmp_path, capsys):
    from aefabmap.cli.demo import default_bundle

    images, gt = generate_loop_sequence(6, seed=1, size=(320, 240))
    write_sequence(tmp_path / "seq", images, gt)
    frames = tmp_path / "short.jsonl"
    frames.write_text("".join(json.dumps({"frame": i, "verified": False, "candidates": []}) + "\n" for i in range(4)))
    code = sdr.main(["--second", str(default_bundle()), "--images", str(tmp_path / "seq"), "--gt",
                     str(tmp_path / "seq" / "gt.npy"), "--frames", str(frames)])
    assert code == 2 and "one record per image" in capsys.readouterr().out
