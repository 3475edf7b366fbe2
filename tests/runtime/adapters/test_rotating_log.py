"""The node's log set: never overwritten, rotated, kept within a budget, degraded on low space,
write errors counted and survived (runtime/aefabmap_runtime/adapters/rotating_log.py)."""

from __future__ import annotations

import errno
import os
import shutil
import socket
import threading

import pytest
from mcap.reader import make_reader

from aefabmap_runtime.errors import ConfigError, LogError, TransportError
from aefabmap_runtime.adapters.log_set import LOG_FILE_METADATA, LogSet, LogSetReader, log_files
from aefabmap_runtime.adapters.mcap_log import (
    LOG_METADATA,
    MANIFEST_METADATA,
    RUN_CONFIG_METADATA,
    McapLogReader,
    McapLogWriter,
)
from aefabmap_runtime.adapters.node import NodeOptions, run_node
from aefabmap_runtime.adapters.rotating_log import MB, LogRotationConfig, RotatingLog
from aefabmap_runtime.adapters.zenoh_transport import SessionConfig

from .stream_fakes import FakeDetector, make_result, mounted_tmpfs

PAYLOAD = 20_000  # bytes of one logged "image": random, so compression does not shrink it
T0 = 1_700_000_000_000_000_000
NO_LIMITS = {"images_min_free_mb": 0.0, "results_min_free_mb": 0.0}


def _write_frames(log, n, start=0, after_each=None):
    for i in range(start, start + n):
        log.write_image(os.urandom(PAYLOAD), "image/jpeg", T0 + i * 10**8, sequence=i)
        log.write_result(make_result(i, T0 + i * 10**8))
        if after_each is not None:
            after_each(i)


def _plain_read(path):
    """Messages per topic and metadata names, read by the mcap package's own reader (with summary)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and len(summary.schemas) == 3 and len(summary.channels) == 3
        topics: dict[str, int] = {}
        for _, channel, _ in reader.iter_messages():
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
        names = {m.name for m in reader.iter_metadata()}
    return topics, names


def test_an_existing_log_is_never_overwritten(tmp_path):
    old = tmp_path / "run.mcap"
    old.write_bytes(b"yesterday's log")
    with RotatingLog(old, rotation=LogRotationConfig(**NO_LIMITS)).open() as log:
        _write_frames(log, 3)
    assert old.read_bytes() == b"yesterday's log"
    assert log.files == [tmp_path / "run-0001.mcap"] and log.errors == 0
    with RotatingLog(old, rotation=LogRotationConfig(**NO_LIMITS)).open() as again:
        pass
    assert again.files == [tmp_path / "run-0002.mcap"]
    with pytest.raises(LogError, match="does not exist"):
        RotatingLog(tmp_path / "missing" / "run.mcap")
    assert sorted(os.listdir(tmp_path)) == ["run-0001.mcap", "run-0002.mcap", "run.mcap"]


def test_rotated_files_are_each_a_complete_log_and_read_as_one_run(tmp_path):
    rotation = LogRotationConfig(max_mb=0.5, **NO_LIMITS)
    with RotatingLog(tmp_path / "run-{n}.mcap", rotation=rotation, manifest={"detector": "fake"},
                     run_config={"model": "m"}).open() as log:
        _write_frames(log, 120)
        log.write_stats({"note": "a dict is logged as it is"})
    files = log_files(tmp_path)
    assert files == log.files and len(files) >= 4
    assert [p.name for p in files[:2]] == ["run-0001.mcap", "run-0002.mcap"]
    total = {}
    for path in files:
        assert path.stat().st_size <= 0.5 * MB
        topics, names = _plain_read(path)
        assert {MANIFEST_METADATA, RUN_CONFIG_METADATA, LOG_METADATA, LOG_FILE_METADATA} <= names
        assert topics["/camera/image"] == topics["/lcd/result"]  # a frame's image and result share a file
        for k, v in topics.items():
            total[k] = total.get(k, 0) + v
    assert total == {"/camera/image": 120, "/lcd/result": 120, "/lcd/stats": 1}
    reader = LogSetReader(files)
    frames = list(reader.frames())
    assert [f.stamp_ns for f in frames] == [T0 + i * 10**8 for i in range(120)]
    assert [r.sequence for r in reader.results] == list(range(120))
    assert reader.runs == 1 and reader.manifest == {"detector": "fake"} and not reader.status.truncated
    assert reader.status.images_read == 120 and len(reader.status.files) == len(files)
    meta = [McapLogReader(p) for p in files]
    for r in meta:
        list(r.frames())
    assert [r.metadata[LOG_FILE_METADATA]["index"] for r in meta] == list(range(1, len(files) + 1))
    assert meta[1].metadata[LOG_FILE_METADATA]["previous"] == "run-0001.mcap"


def test_the_budget_deletes_the_oldest_closed_files_of_the_set_only(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    precious = tmp_path / "precious.mcap"
    shutil.copyfile(_empty_log(tmp_path / "src.mcap"), precious)
    (logs / "lcd-20000101-000000-0001.mcap").symlink_to(precious)  # our name, but a symlink: left alone
    other = logs / "notes.mcap"
    shutil.copyfile(precious, other)  # an MCAP file not named like ours: left alone
    rotation = LogRotationConfig(max_mb=0.5, budget_mb=1.5, **NO_LIMITS)
    sizes = []

    def measure(_):
        sizes.append(sum(f.size for f in LogSet(str(logs) + "/").files()))

    with RotatingLog(str(logs) + "/", rotation=rotation).open() as log:
        _write_frames(log, 200, after_each=measure)
    assert max(sizes) <= 1.5 * MB
    assert len(log.files) >= 6 and len(log.deleted) >= 3
    assert log.files[0].name.endswith("-0002.mcap")  # after the symlink's number
    left = LogSet(str(logs) + "/").files()
    assert [f.path for f in left] == log.files[-len(left):]  # the newest survive
    assert precious.exists() and other.exists() and (logs / "lcd-20000101-000000-0001.mcap").is_symlink()
    for f in left:
        _plain_read(f.path)


def _empty_log(path):
    with McapLogWriter(path):
        pass
    return path


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_low_disk_space_stops_images_then_results_and_logging_resumes(tmp_path):
    free = {"bytes": 10_000 * MB}
    clock = _Clock()
    rotation = LogRotationConfig(images_min_free_mb=50, results_min_free_mb=10, space_check_interval_s=1)
    log = RotatingLog(tmp_path / "run.mcap", rotation=rotation, free_space=lambda _d: free["bytes"], clock=clock)
    log.open()
    states = []

    def step(i, free_mb):
        free["bytes"] = int(free_mb * MB)
        clock.t += 1.5
        _write_frames(log, 1, start=i)
        log.write_stats({"i": i})
        states.append(log.state)

    for i, free_mb in enumerate([1000, 40, 40, 5, 5, 1000]):
        step(i, free_mb)
    log.close()
    assert states == ["ok", "images_stopped", "images_stopped", "stopped", "stopped", "ok"]
    assert log.images_written == 2 and log.images_skipped == 4 and log.messages_skipped == 4 and log.errors == 0
    reader = McapLogReader(tmp_path / "run.mcap")
    assert [f.sequence for f in reader.frames()] == [0, 5]
    assert [r.sequence for r in reader.results] == [0, 1, 2, 5]


class _FailingRaw:
    """A file object that fails like a full disk once ``room`` bytes have been written."""

    def __init__(self, inner, room):
        self.inner, self.room = inner, room

    def write(self, data):
        if self.room <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        n = self.inner.write(bytes(data)[: self.room])
        self.room -= n
        return n

    def close(self):
        self.inner.close()


def test_a_write_error_is_counted_the_file_abandoned_and_a_new_one_tried(tmp_path):
    clock = _Clock()
    made = []

    def factory(*args, **kwargs):
        w = McapLogWriter(*args, **kwargs)
        if not made:  # the first file fails after ~400 KB (one chunk fits), like a disk filling up
            w._file._f = _FailingRaw(w._file._f, 400_000)
        made.append(w)
        return w

    rotation = LogRotationConfig(retry_interval_s=5, **NO_LIMITS)
    log = RotatingLog(tmp_path / "run.mcap", None, rotation,
                      writer_factory=factory, clock=clock).open()
    _write_frames(log, 40)  # 800 KB: never raises
    assert log.errors >= 1 and log.state == "failed" and "No space left" in log.last_error
    skipped = log.images_skipped
    _write_frames(log, 2, start=40)  # within the retry interval: skipped, no new file
    assert log.images_skipped == skipped + 2 and len(log.files) == 1
    clock.t += 6
    _write_frames(log, 5, start=42)
    log.close()
    assert log.state == "closed" and log.files == [tmp_path / "run.mcap", tmp_path / "run-0001.mcap"]
    first = McapLogReader(log.files[0])
    list(first.frames())
    assert first.status.truncated and 0 < len(first.results) < 40  # readable up to the failure
    second = McapLogReader(log.files[1])
    assert [f.sequence for f in second.frames()] == list(range(42, 47))
    assert not second.status.truncated


def test_rotation_config_is_checked():
    with pytest.raises(ConfigError, match="budget"):
        LogRotationConfig(max_mb=10, budget_mb=5)
    for bad in (-1, 0, float("nan"), float("inf"), "5", True):
        with pytest.raises(ConfigError, match="max_mb"):
            LogRotationConfig(max_mb=bad)
    for bad in (-1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="min_free_mb"):
            LogRotationConfig(results_min_free_mb=bad)
        with pytest.raises(ConfigError, match="budget_mb"):
            LogRotationConfig(budget_mb=bad)
    assert LogRotationConfig(images_min_free_mb=0, results_min_free_mb=0).images_threshold_bytes == 0
    with pytest.raises(ConfigError, match="max_mb must be >="):
        LogRotationConfig(max_mb=0.01)
    assert LogRotationConfig(max_mb=5).images_threshold_bytes == 500 * MB
    assert LogRotationConfig(max_mb=1000).images_threshold_bytes == 2000 * MB
    assert LogRotationConfig(max_mb=1).chunk_size(256 * 1024) == 128 * 1024


def test_a_failed_start_creates_no_file_and_touches_no_log(tmp_path):
    """The log is opened only once the session is up: a start that fails leaves the directory as it was."""
    old = tmp_path / "run.mcap"
    old.write_bytes(b"previous run")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        options = NodeOptions("robot/camera/image", old, SessionConfig(listen=(f"tcp/127.0.0.1:{port}",)))
        with pytest.raises(TransportError):
            run_node(FakeDetector(), options, stop_event=threading.Event())
    assert os.listdir(tmp_path) == ["run.mcap"] and old.read_bytes() == b"previous run"


@pytest.fixture
def tiny_disk(tmp_path):
    """A 1 MiB tmpfs (needs root and mount; skipped elsewhere)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, "1m"):
        yield disk


def test_a_full_disk_is_survived_and_a_budget_keeps_it_from_filling(tiny_disk):
    unbounded = RotatingLog(tiny_disk / "full.mcap", rotation=LogRotationConfig(**NO_LIMITS)).open()
    _write_frames(unbounded, 100)  # 2 MB into a 1 MiB disk: never raises
    unbounded.close()
    assert unbounded.errors >= 1 and "No space left" in unbounded.last_error
    first = McapLogReader(unbounded.files[0])
    list(first.frames())
    assert len(first.results) > 10  # what fit is readable
    for p in list(tiny_disk.iterdir()):
        p.unlink()
    bounded = RotatingLog(tiny_disk / "run.mcap",
                          rotation=LogRotationConfig(max_mb=0.25, budget_mb=0.75, **NO_LIMITS)).open()
    _write_frames(bounded, 100)
    bounded.close()
    assert bounded.errors == 0 and len(bounded.deleted) >= 3
    for f in LogSet(tiny_disk / "run.mcap").files():
        _plain_read(f.path)
    # a disk already full at start: the node starts anyway, the log counts the error and retries
    for p in list(tiny_disk.iterdir()):
        p.unlink()
    with open(tiny_disk / "filler", "wb") as filler, pytest.raises(OSError):
        while True:
            filler.write(b"\0" * 65536)
    full = RotatingLog(tiny_disk / "late.mcap", rotation=LogRotationConfig(**NO_LIMITS)).open()
    assert full.state == "failed" and full.errors == 1 and full.files == []
    _write_frames(full, 3)
    full.close()
    assert [p.name for p in tiny_disk.iterdir()] == ["filler"]  # no debris left by the failed attempts
