"""`aefabmap bench soak`: a real `aefabmap run` node fed synthetic frames over loopback Zenoh, its RSS
sampled at the requested frame counts, its log rotating within the budget (tiny counts)."""

from __future__ import annotations

import json

import pytest

from aefabmap.cli.main import main


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_bench_soak_pipeline_phase(tmp_path, capsys):
    out = tmp_path / "soak.json"
    work = tmp_path / "work"
    code = main([
        "bench", "soak", "--frames", "160", "--observations", "0", "--max-places", "20", "--rate", "0",
        "--size", "320x240", "--mcap-max-mb", "0.3", "--log-budget-mb", "0.9", "--frame-checkpoints", "40", "80",
        "--warmup-frames", "80", "--sample-seconds", "1", "--workdir", str(work), "--json", str(out),
    ])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "soak" and doc["core"] is None
    p = doc["pipeline"]
    # RSS of the node at every requested count, and at the last one.
    assert list(p["rss_mb_at"]) == ["40", "80", "160"]
    assert all(isinstance(v, float) and v > 30 for v in p["rss_mb_at"].values())
    assert [s["frames"] for s in p["checkpoints"]] == [40, 80, 160]
    assert all(s["log_files"] >= 1 and s["log_bytes"] > 0 for s in p["checkpoints"])
    assert p["frames_published"] == 160 and 0 < p["frames_processed"] <= 160
    assert p["not_processed"] == 160 - p["frames_processed"]
    # The cap holds and places were evicted (160 frames - exclude 50 - cap 20).
    assert p["places"]["max"] == 20 and p["evictions"] >= 160 - 50 - 20 - p["not_processed"]
    # The log rotated and the budget deleted old files; what is left fits the budget.
    lg = p["log"]
    assert lg["files_created"] >= 3 and lg["files_deleted"] >= 1 and lg["errors"] == 0
    assert lg["dir_end"]["bytes"] <= 0.9 * 2**20 and lg["dir_end"]["files"] == len(list((work / "log").glob("*.mcap")))
    assert p["node_summary"]["frames_processed"] == p["frames_processed"]
    assert set(p["rss_flat"]) >= {"warmup", "samples", "range_mb", "growth_mb", "met"}
    assert p["rss_flat"]["samples"] >= 1
    text = capsys.readouterr().out
    assert "pipeline: RSS MB at frames" in text and "log files created" in text


def test_bench_soak_refuses_a_bad_size(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "soak", "--size", "320by240"])
    assert exc.value.code == 2
    assert "size must be WxH" in capsys.readouterr().err
