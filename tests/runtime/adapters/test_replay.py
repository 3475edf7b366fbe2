"""Replay and --check (runtime/adapters/replay.py) on live logs, truncated logs and ROS 2 bags."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from aefabmap.runtime.adapters.mcap_log import (
    McapLogConfig,
    McapLogReader,
    McapLogWriter,
)
from aefabmap.runtime.adapters.replay import (
    NONDETERMINISTIC_FIELDS,
    compare_results,
    replay,
)
from aefabmap.runtime.adapters.zenoh_transport import open_session
from aefabmap.runtime.tools.publisher import array_source, publish_frames

from .stream_fakes import (
    FakeDetector,
    JsonCollector,
    NodeThread,
    sample_images,
    session_pair,
    write_ros2_bag,
)

pytestmark = pytest.mark.timeout(90)
KEY = "robot/camera/image"


@pytest.fixture(scope="module")
def live_log(tmp_path_factory):
    """A log recorded by the live node: 16 frames of a two-lap synthetic loop (jpeg + raw)."""
    path = tmp_path_factory.mktemp("live") / "live.mcap"
    listen, connect = session_pair()
    images = sample_images(16, size=(96, 72))
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=path,
                    queue_size=32, stats_period_s=0.5) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, "robot/camera/lcd")
            publish_frames(connect, KEY, array_source(images[:8], "jpeg"), rate_hz=200, wait_for_subscriber_s=10)
            publish_frames(connect, KEY, array_source(images[8:], "mono8"), rate_hz=200, wait_for_subscriber_s=10)
            results.wait_for(lambda d: d["sequence"] == 15, timeout_s=30)
            results.close()
        summary = node.finish()
    assert summary.frames_processed == 16
    return path


def test_replay_of_a_live_log_checks_ok_and_writes_a_new_log(live_log, tmp_path):
    out = tmp_path / "replayed.mcap"
    summary = replay(FakeDetector(), live_log, out_path=out, check=True)
    assert summary.frames_read == 16 and summary.frames_processed == 16
    assert summary.check is not None and summary.check.ok, summary.check.describe()
    assert summary.check.compared == 16 and summary.check.complete
    assert summary.loops > 0  # the second lap revisits the first
    assert "check OK" in summary.check.describe()
    json.dumps(summary.to_dict(), default=str)
    # the new log replays to the same results again
    again = replay(FakeDetector(), out, check=True)
    assert again.check.ok and again.check.compared == 16


def test_check_reports_differences(live_log):
    summary = replay(FakeDetector(threshold=0.5), live_log, check=True)
    report = summary.check
    assert not report.ok and report.mismatched > 0
    assert "loop" in report.field_counts or "inserted_place" in report.field_counts
    assert report.mismatches and set(report.mismatches[0]) == {"sequence", "field", "logged", "replayed"}
    assert "differ" in report.describe()
    assert any("manifest differs" in n for n in report.notes)


def test_compare_results_rules():
    a = [{"sequence": i, "stamp_ns": i, "p_new": 0.1 * i, "loop": False, "timings_ms": {"x": i}} for i in range(4)]
    b = [dict(d, timings_ms={"x": 99}, p_new=d["p_new"] * (1 + 1e-9)) for d in a]
    r = compare_results(a, b)
    assert r.ok and r.compared == 4  # timings ignored, float tolerance
    b[2]["loop"] = True
    r = compare_results(a, b)
    assert not r.ok and r.field_counts == {"loop": 1} and r.mismatches[0]["sequence"] == 2
    r = compare_results(a, b[:3] + [], fields=("stamp_ns",))
    assert r.only_in_log == 1 and not r.ok
    r = compare_results(a, a[:3], truncated=True)
    assert r.ok and r.tail_ignored == 1
    assert {"timings_ms", "latency_ms", "frame_seq"} <= set(NONDETERMINISTIC_FIELDS)
    # a field only one side has is a difference (format drift), an ignored one is not
    c = [dict(d, n_places=1, latency_ms=5.0, frame_seq=7) for d in a]
    r = compare_results(a, c)
    assert r.field_counts == {"n_places": 4}


def test_replay_of_a_truncated_log(live_log, tmp_path):
    data = live_log.read_bytes()
    # rewrite with small chunks so that a cut keeps several complete chunks
    small = tmp_path / "small.mcap"
    src = McapLogReader(live_log)
    with McapLogWriter(small, McapLogConfig(chunk_size=2048), manifest=FakeDetector().manifest) as w:
        frames = list(src.frames())
        for f, res in zip(frames, src.results):
            w.write_image(f.payload, f.encoding, f.stamp_ns, sequence=f.sequence)
            w.write_result(res)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(small.read_bytes()[: int(small.stat().st_size * 0.6)])
    summary = replay(FakeDetector(), cut, check=True)
    assert summary.status.truncated and 0 < summary.frames_processed < 16
    assert summary.check.ok, summary.check.describe()
    assert any("truncated" in n for n in summary.check.notes)
    assert len(data) > 0


def test_sparse_image_log_is_flagged_incomplete(tmp_path):
    path = tmp_path / "sparse.mcap"
    det = FakeDetector()
    images = sample_images(6, size=(64, 48))
    from aefabmap.runtime.adapters.frames import encode_frame

    with McapLogWriter(path, McapLogConfig(image_every=2)) as w:
        for i, img in enumerate(images):
            payload, enc = encode_frame(img, "png")
            res = det.process(img, i).to_dict()
            w.write_image(payload, enc, i, sequence=i)
            w.write_result(res)
    summary = replay(FakeDetector(), path, check=True)
    assert summary.frames_processed == 3
    assert not summary.check.complete and not summary.check.ok
    assert any("image_every" in n for n in summary.check.notes)


def test_ros2_bag_replays(tmp_path):
    images = sample_images(10, size=(96, 72))
    bag = tmp_path / "ros2.mcap"
    stamps = write_ros2_bag(bag, images)
    seen = []
    summary = replay(FakeDetector(), bag, on_result=seen.append)
    assert summary.frames_processed == 10 and summary.status.image_topic == "/cam/compressed"
    assert [d["stamp_ns"] for d in seen] == stamps
    raw = replay(FakeDetector(), bag, image_topic="/cam/raw", out_path=tmp_path / "from_raw.mcap")
    assert raw.frames_processed == 10 and sum(raw.bad.values()) == 0
    r = McapLogReader(tmp_path / "from_raw.mcap")
    out_frames = list(r.frames())
    assert len(out_frames) == 10 and out_frames[0].encoding == "image/png"
    assert all(np.array_equal(f.decode(), img) for f, img in zip(out_frames, images))
    # no results in a bag: --check has nothing to compare
    checked = replay(FakeDetector(), bag, check=True)
    assert not checked.check.ok and any("no /lcd/result" in n for n in checked.check.notes)


def test_cli_replay_main(live_log, tmp_path, monkeypatch, capsys):
    import aefabmap.runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap.cli import replay as cli_replay

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    args = argparse.Namespace(log=str(live_log), model="fake", out=str(tmp_path / "o.mcap"), check=True)
    assert cli_replay.main(args) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["check"]["ok"] and doc["frames_processed"] == 16
    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector(threshold=0.5))
    assert cli_replay.main(args) == 1
    args = argparse.Namespace(log=str(tmp_path / "missing.mcap"), model="fake", out=None, check=False)
    assert cli_replay.main(args) == 6  # LogError exit code


def test_real_detector_live_then_replay_check(tmp_path):
    """The lead's LoopClosureDetector on a small synthetic bundle: live log -> replay --check OK."""
    from aefabmap.runtime.adapters.bundle_reader import load_detector
    from aefabmap.runtime.core.detector import DetectorConfig
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    config = DetectorConfig(exclude=2)
    listen, connect = session_pair()
    log_path = tmp_path / "real.mcap"
    images = sample_images(20, size=(160, 120))
    with NodeThread(detector=load_detector(bundle, config), session_config=listen, key=KEY,
                    mcap_path=log_path, queue_size=32, stats_period_s=1.0) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, "robot/camera/lcd")
            publish_frames(connect, KEY, array_source(images, "jpeg"), rate_hz=100, wait_for_subscriber_s=10)
            docs = results.wait_for(lambda d: d["sequence"] == 19, timeout_s=60)
            results.close()
        summary = node.finish()
    assert summary.frames_processed == 20 and summary.bad_total == 0
    assert any(d["inserted_place"] is not None for d in docs)
    replayed = replay(load_detector(bundle, config), log_path, check=True)
    assert replayed.check.ok, replayed.check.describe()
    assert replayed.check.compared == 20
