"""`aefabmap train` / `eval` / `bench` end to end through the CLI, on real data when present."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from aefabmap.cli.main import main
from aefabmap_runtime.adapters.bundle_reader import load_bundle

REQUIRED_KEYS = ("recall_at_100p", "auc", "max_f1", "recall_at_100p_tolerant", "auc_tolerant", "max_f1_tolerant", "frames", "ms_per_frame")


@pytest.fixture(scope="module")
def small_train_dir(tmp_path_factory, train_images):
    """40 CamVid frames: enough for a small vocabulary, fast enough for every CI run."""
    d = tmp_path_factory.mktemp("train")
    for p in train_images[::17][:40]:
        shutil.copy(p, d / p.name)
    return d


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory, small_train_dir):
    out = tmp_path_factory.mktemp("bundles") / "orb100"
    args = ["train", "--images", str(small_train_dir), "--features", "orb", "--words", "100",
            "--max-descriptors", "10000", "--seed", "3", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    return out


@pytest.mark.data
@pytest.mark.slow
def test_train_is_deterministic(small_bundle, small_train_dir, tmp_path):
    again = tmp_path / "again"
    args = ["train", "--images", str(small_train_dir), "--features", "orb", "--words", "100",
            "--max-descriptors", "10000", "--seed", "3", "--out", str(again), "--no-progress"]
    assert main(args) == 0
    a, b = load_bundle(small_bundle), load_bundle(again)
    assert a.manifest["files"] == b.manifest["files"]
    assert a.manifest == {**b.manifest, "files": a.manifest["files"]}


@pytest.mark.data
@pytest.mark.slow
def test_eval_on_a_real_sequence(small_bundle, lip6, tmp_path):
    """Evaluate on the first 300 Lip6 frames with a matching slice of the ground truth."""
    frames = sorted(lip6.glob("*.jpg"))[:300]
    seq = tmp_path / "seq"
    seq.mkdir()
    for p in frames:
        (seq / p.name).symlink_to(p)
    gt = np.load(lip6 / "ground_truth.npy")[:300, :300]
    gt_path = tmp_path / "gt.npy"
    np.save(gt_path, gt)
    out = tmp_path / "eval.json"
    code = main(["eval", "--model", str(small_bundle), "--images", str(seq), "--gt", str(gt_path),
                 "--scorer", "both", "--json", str(out), "--plot", str(tmp_path / "pr.png"),
                 "--score-matrix", str(tmp_path / "m.png"), "--no-progress"])
    assert code == 0
    doc = json.loads(out.read_text())
    for key in REQUIRED_KEYS:
        assert key in doc, key
    assert doc["frames"] == 300
    assert set(doc["ms_per_frame"]) >= {"decode", "features", "quantise", "inference", "total"}
    assert doc["ms_per_frame"]["features"]["p95"] >= doc["ms_per_frame"]["features"]["median"] > 0
    assert set(doc["methods"]) == {"fabmap", "bow"}
    assert (tmp_path / "pr.png").stat().st_size > 1000 and (tmp_path / "m.png").stat().st_size > 1000


@pytest.mark.data
@pytest.mark.slow
def test_eval_refuses_mismatched_ground_truth(small_bundle, lip6, tmp_path, caplog):
    gt_path = tmp_path / "gt.npy"
    np.save(gt_path, np.zeros((5, 5), bool))
    code = main(["eval", "--model", str(small_bundle), "--images", str(lip6), "--gt", str(gt_path), "--no-progress"])
    assert code == 4
    assert "ground truth" in caplog.text


def test_eval_refuses_a_missing_bundle(tmp_path, caplog):
    (tmp_path / "imgs").mkdir()
    code = main(["eval", "--model", str(tmp_path / "nope"), "--images", str(tmp_path / "imgs"), "--gt", str(tmp_path / "gt.npy")])
    assert code in (3, 4)


def test_bench_inference_json(tmp_path):
    out = tmp_path / "b.json"
    assert main(["bench", "inference", "--places", "200", "--words", "2000", "--queries", "20", "--json", str(out)]) == 0
    assert main(["bench", "inference", "--places", "50", "--words", "500", "--queries", "5", "--scatter", "numpy",
                 "--json", str(tmp_path / "n.json")]) == 0
    assert json.loads((tmp_path / "n.json").read_text())["scatter"] == "numpy"
    doc = json.loads(out.read_text())
    assert {"median_ms", "p95_ms", "bytes_per_place", "add_ms_median", "remove_ms_median"} <= set(doc)
    assert doc["remove_ms_median"] > 0
    assert doc["places"] == 200 and doc["bytes_per_place"] > 0


def test_bench_chowliu_json(tmp_path):
    out = tmp_path / "c.json"
    assert main(["bench", "chowliu", "--words", "500", "--images", "200", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["seconds"] > 0


def test_eval_refuses_a_malformed_camera(tmp_path, caplog):
    (tmp_path / "imgs").mkdir()
    code = main(["eval", "--model", str(tmp_path / "nope"), "--images", str(tmp_path / "imgs"),
                 "--gt", str(tmp_path / "gt.npy"), "--camera", "400,400,320"])
    assert code != 0
    assert "camera" in caplog.text


@pytest.mark.timeout(300)
def test_eval_with_two_workers_writes_the_same_records(tmp_path):
    """eval --workers 2: the per-frame evidence and the metrics of --workers 1 (timings aside)."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    seq = tmp_path / "seq"
    make_demo_sequence(seq, n_frames=30, seed=2, size=(320, 240))
    gt = np.zeros((30, 30), bool)
    gt_path = tmp_path / "gt.npy"
    np.save(gt_path, gt)
    docs, records = {}, {}
    for workers in ("1", "2"):
        out, frames = tmp_path / f"w{workers}.json", tmp_path / f"w{workers}.jsonl"
        assert main(["eval", "--model", str(default_bundle()), "--images", str(seq), "--gt", str(gt_path),
                     "--exclude", "3", "--workers", workers, "--json", str(out), "--frames", str(frames),
                     "--no-progress"]) == 0
        docs[workers] = _without_timing(json.loads(out.read_text()))
        records[workers] = frames.read_text()
    assert records["1"] == records["2"] and len(records["1"].splitlines()) == 30
    assert docs["1"] == docs["2"]


def _without_timing(doc):
    """An eval document without what differs from run to run (times, memory)."""
    if isinstance(doc, dict):
        return {k: _without_timing(v) for k, v in doc.items()
                if k not in ("ms_per_frame", "verification_ms", "wall_s", "peak_rss_mb")}
    return doc
