"""A live node writing a rotated, budgeted log over loopback Zenoh, then replaying the set."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.reader import make_reader

import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
from aefabmap.cli import replay as cli_replay
from aefabmap_runtime.adapters.log_set import LogSet, log_files
from aefabmap_runtime.adapters.mcap_log import McapLogReader
from aefabmap_runtime.adapters.replay import replay
from aefabmap_runtime.adapters.rotating_log import MB, LogRotationConfig
from aefabmap_runtime.adapters.zenoh_transport import open_session
from aefabmap_runtime.tools.publisher import array_source, publish_frames

from tests.conftest import cli_args

from .stream_fakes import (
    KEY,
    FakeDetector,
    JsonCollector,
    NodeThread,
    mounted_tmpfs,
    sample_images,
    session_pair,
)

pytestmark = pytest.mark.timeout(120)
NO_LIMITS = {"images_min_free_mb": 0.0, "results_min_free_mb": 0.0}


def _record(target, images, n_frames, rotation, fmt="jpeg", results_seen=None):
    """Run the node on ``target`` while ``n_frames`` frames (``images`` looped) are published;
    returns (run summary, last stats message seen on Zenoh). results_seen: a list to which the
    results published on Zenoh are appended."""
    listen, connect = session_pair()
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=target,
                    queue_size=n_frames, stats_period_s=0.2, log_rotation=rotation) as node:
        with open_session(connect) as s:
            stats = JsonCollector(s, "robot/camera/lcd/stats")
            results = JsonCollector(s, "robot/camera/lcd")
            pub = publish_frames(connect, KEY, array_source(images, fmt), rate_hz=150, count=n_frames,
                                 loop=True, wait_for_subscriber_s=10)
            assert pub.published == n_frames
            docs = stats.wait_for(lambda d: d["frames_processed"] + d["dropped"] == n_frames, timeout_s=60)
            done = docs[-1]["frames_processed"]
            published = results.wait_for(lambda d: d["sequence"] == done - 1, timeout_s=30)
            stats.close()
            results.close()
        summary = node.finish()
    if results_seen is not None:
        results_seen.extend(published)
    return summary, docs[-1]


def test_a_rotated_log_replays_as_one_run_and_checks_ok(tmp_path, monkeypatch):
    logs = tmp_path / "logs"
    logs.mkdir()
    summary, last_stats = _record(str(logs) + "/", sample_images(24, size=(160, 120)), 60,
                                  LogRotationConfig(max_mb=0.25, **NO_LIMITS), fmt="png")
    assert summary.frames_processed == 60 and summary.log_errors == 0
    assert len(summary.log_files) >= 2 and summary.mcap_path == summary.log_files[0]
    assert last_stats["log_errors"] == 0 and last_stats["log_state"] == "ok"
    assert log_files(logs) == [Path(p) for p in summary.log_files]
    result = replay(FakeDetector(), logs, check=True)
    assert result.frames_processed == 60 and result.check.ok, result.check.describe()
    assert result.check.compared == 60 and len(result.status.files) == len(summary.log_files)
    # the command line takes a glob (or a directory, or several files) the same way
    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    args = cli_args("replay", logs / "lcd-*.mcap", "--model", "fake", "--check")
    assert cli_replay.main(args) == 0


@pytest.mark.slow
def test_a_budgeted_log_never_passes_its_budget_and_every_closed_file_reads(tmp_path):
    """~300 frames of 640x480 JPEG (~19 MB) into files of 1 MB within a 4 MB budget."""
    logs = tmp_path / "logs"
    logs.mkdir()
    rotation = LogRotationConfig(max_mb=1, budget_mb=4, **NO_LIMITS)
    summary, last_stats = _record(str(logs) + "/", sample_images(30, size=(640, 480)), 300, rotation)
    # (a loaded machine may drop a frame in transport: counted, not the log's doing)
    done = summary.frames_processed
    assert done + summary.dropped == 300 and done >= 290
    assert summary.images_logged == done and summary.log_errors == 0
    assert last_stats["log_state"] == "ok"
    left = LogSet(str(logs) + "/").files()
    on_disk = sum(f.size for f in left)
    assert on_disk <= 4 * MB
    assert summary.log_files_deleted >= 10 and len(left) == len(summary.log_files) - summary.log_files_deleted
    images = 0
    for f in left:
        assert f.size <= 1 * MB
        with open(f.path, "rb") as fh:  # the mcap package's own reader, with the summary section
            reader = make_reader(fh)
            assert reader.get_summary() is not None
            images += sum(1 for _, ch, _ in reader.iter_messages(topics=["/camera/image"]))
    result = replay(FakeDetector(), logs, check=True)
    assert result.frames_processed == images > 0
    assert any("deleted by the log budget" in n for n in result.check.notes)
    last = McapLogReader(left[-1].path)
    list(last.frames())
    assert last.results[-1].sequence == done - 1
    json.dumps(result.to_dict(), default=str)


def test_a_full_disk_never_stops_detection_and_shows_in_the_stats(tmp_path):
    """The node logs onto a 1 MiB tmpfs that fills after a few frames: every frame is still
    processed and published; the stats say log_errors > 0 and log_state 'failed'."""
    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, "1m"):
        published = []
        summary, last_stats = _record(disk / "run.mcap", sample_images(16, size=(320, 240)), 120,
                                      LogRotationConfig(**NO_LIMITS), fmt="png", results_seen=published)
        # (a loaded machine may drop a frame in transport: counted, not the log's doing)
        done = summary.frames_processed
        assert done + summary.dropped == 120 and done >= 110 and [d["sequence"] for d in published] == list(range(done))
        assert summary.log_errors >= 1 and last_stats["log_errors"] >= 1 and last_stats["log_state"] == "failed"
        reader = McapLogReader(disk / "run.mcap")
        list(reader.frames())
        assert 0 < len(reader.results) < done  # what fit before the disk was full is readable
