"""Plumbing of `aefabmap bench pipeline` and `aefabmap bench stream` (tiny counts; no timing asserts)."""

from __future__ import annotations

import json

import pytest

from aefabmap.cli.main import main
from aefabmap_runtime.errors import BundleError, ConfigError
from aefabmap_runtime.tools.stream_bench import (
    PipelineBenchConfig,
    StreamBenchConfig,
    bench_stream,
)


def _sane_stats(s: dict) -> None:
    assert s["n"] > 0
    assert 0 <= s["median"] <= s["p95"] <= s["max"]


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_bench_pipeline_writes_json(tmp_path, capsys):
    out = tmp_path / "pipeline.json"
    code = main(["bench", "pipeline", "--places", "60", "--frames", "4", "--warmup", "1", "--verify-bruteforce", "1",
                 "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "pipeline" and doc["single_core"] is True
    assert doc["verify_bruteforce"] == 1  # the candidates retried, as the option set them
    assert doc["places_in_map"]["max"] >= 60 - 50  # delayed insertion keeps the last `exclude` pending
    assert doc["threads_env"]["OMP_NUM_THREADS"] == "1" and doc["cv2_threads"] == 1
    for stage in ("decode", "features", "quantise", "inference", "verification"):
        assert stage in doc["stages_ms"] and stage in doc["stages_cpu_ms"]
    _sane_stats(doc["total_ms"])
    _sane_stats(doc["stages_ms"]["features"])
    assert doc["frames_timed"] == 4
    assert doc["keypoints_median"] > 100  # ORB on a textured 640x480 frame
    # Pre-filled places carry keypoints, so frames verify candidates as in a live map.
    assert doc["place_keypoints"] is True and doc["places_verified_per_frame"]["median"] >= 1
    assert set(doc["target"]) == {"median_total_ms_le", "met_wall", "met_cpu"}
    assert "target median <= 10 ms" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_bench_stream_two_processes(tmp_path, capsys):
    out = tmp_path / "stream.json"
    code = main([
        "bench", "stream", "--seconds", "1.5", "--throughput-seconds", "1.5", "--flood-seconds", "1",
        "--soak-seconds", "2", "--max-places", "5", "--frames", "12", "--image-every", "0",
        "--workdir", str(tmp_path / "work"), "--json", str(out),
    ])
    assert code == 0
    doc = json.loads(out.read_text())
    assert set(doc["phases"]) == {"throughput", "rate", "flood", "soak"}
    for name, ph in doc["phases"].items():
        assert 0 < ph["processed"] <= ph["published"], name
        assert ph["not_processed"] == ph["published"] - ph["processed"]
        _sane_stats(ph["latency_ms"])
        assert ph["latency_ms"]["median"] < 10_000  # same clock: no absurd stamps
    assert doc["phases"]["throughput"]["fps"] > 0
    flood = doc["phases"]["flood"]
    assert flood["publish_rate_hz"] > doc["phases"]["rate"]["publish_rate_hz"]
    # The cap was reached and honoured.
    assert doc["phases"]["soak"]["places"]["max"] <= 5
    r = doc["rss_mb"]
    assert r["samples"] > 0 and 0 < r["first"] <= r["max"] and r["last"] <= r["max"]
    assert doc["node_summary"] is not None and doc["node_summary"]["frames_processed"] >= sum(
        ph["processed"] for ph in doc["phases"].values()
    )
    assert set(doc["targets"]) == {"sustained_fps_ge_50", "p95_latency_ms_le_30_at_30hz",
                                   "flood_latency_bounded", "rss_flat_at_cap"}
    assert (tmp_path / "work" / "bench_stream.mcap").is_file()  # --workdir keeps the node's log
    assert "node RSS MB" in capsys.readouterr().out


def test_bench_configs_refuse_bad_values(tmp_path):
    with pytest.raises(ConfigError):
        PipelineBenchConfig(bundle="x", prefill="random")
    with pytest.raises(ConfigError):
        PipelineBenchConfig(bundle="x", verify_bruteforce=-1)
    with pytest.raises(ConfigError):
        StreamBenchConfig(bundle="x", rate_hz=0)
    with pytest.raises(ConfigError):
        StreamBenchConfig(bundle="x", node_threads=0)
    with pytest.raises(BundleError):
        bench_stream(StreamBenchConfig(bundle=str(tmp_path / "missing")))
